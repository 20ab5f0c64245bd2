"""Scoring a policy on level sets, written once for every evaluation: `impulse eval`, the end of `impulse train`,
`impulse train`'s periodic evaluation (`eval.every_updates`) and the evaluator process of a distributed run.

A specification names one or more level sets, comma-separated ("kinetix:s,handmade"), each as `env.levels` takes
it (`engine.levels.sets.load_level_set`). Every level is played `attempts` times from its start, Kinetix's
protocol (`learner.evaluate.evaluate`). Groups are the mean solve rate of each set and Kinetix's own groups
("s_all", "s_h", ... for levels named "<size>/<file>"), so a run's curves read as Kinetix reports its agents.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from impulse.engine.env.spec import EnvParams
from impulse.engine.levels.level import Level
from impulse.engine.levels.sets import LevelSetError, kinetix_group, load_level_set
from impulse.engine.physics.sizes import SceneSizes
from impulse.learner.agent import Agent
from impulse.learner.evaluate import LevelScores, evaluate

Table = dict[str, dict[str, float]]
"""Per level: {"solve_rate", "mean_return", "mean_length"}."""
COLUMN = "eval"
"""Prefix of the evaluation columns of metrics.jsonl (`evaluation_columns`)."""


class LevelSets(NamedTuple):
    """The levels of one or more sets, stacked, with their names and which set each came from."""

    names: list[str]
    levels: Level
    members: dict[str, list[str]]
    """Set specification (as written) -> the names of its levels."""


def set_names(spec: str) -> list[str]:
    """The sets a specification names, in order, without repeats or blanks."""
    return list(dict.fromkeys(part.strip() for part in spec.split(",") if part.strip()))


def load_level_sets(spec: str, sizes: SceneSizes) -> LevelSets:
    """Every level of the sets `spec` names, loaded into `sizes`; a level named by two sets is played once.
    A set's levels that do not fit `sizes` are left out with a warning naming them (`load_level_set`, the same
    for every command). Raises `LevelSetError` naming the set that cannot be loaded."""
    names: list[str] = []
    batches: list[Level] = []
    members: dict[str, list[str]] = {}
    for source in set_names(spec):
        try:
            set_level_names, levels = load_level_set(source, sizes)
        except LevelSetError as err:
            named = str(err).startswith(f"level set {source!r}")  # the loader's message names the set already
            raise LevelSetError(str(err) if named else f"level set {source!r}: {err}") from None
        keep = [i for i, name in enumerate(set_level_names) if name not in names]
        members[source] = list(set_level_names)
        names += [set_level_names[i] for i in keep]
        batches.append(jax.tree.map(lambda x, keep=keep: x[np.asarray(keep, np.int64)], levels))
    if not names:
        raise LevelSetError(f"no levels in {spec!r}")
    levels = jax.tree.map(lambda *parts: jnp.concatenate(parts), *batches)
    return LevelSets(names, levels, members)


def scores_table(names: list[str], scores: LevelScores) -> Table:
    """Per-level scores by level name."""
    return {
        name: {
            "solve_rate": float(scores.solve_rate[i]),
            "mean_return": float(scores.mean_return[i]),
            "mean_length": float(scores.mean_length[i]),
        }
        for i, name in enumerate(names)
    }


def kinetix_groups(table: Table) -> dict[str, float]:
    """Mean solve rate per group as Kinetix logs them for its hand-made sets: "<size>_all" and "<size>_<prefix>"
    (`engine.levels.sets.kinetix_group`), for levels named "<size>/<file>" as the "kinetix:" sets name them."""
    members: dict[str, list[float]] = {}
    for name, scores in table.items():
        if "/" not in name:
            continue
        for group in (f"{name.rpartition('/')[0]}_all", kinetix_group(name)):
            members.setdefault(group, []).append(scores["solve_rate"])
    return {group: float(np.mean(rates)) for group, rates in sorted(members.items())}


def group_means(table: Table, members: dict[str, list[str]] | None = None) -> dict[str, float]:
    """The mean solve rate of each set (`members`, when there is more than one set) and of Kinetix's groups."""
    groups = {}
    if members and len(members) > 1:
        groups = {source: float(np.mean([table[name]["solve_rate"] for name in names]))
                  for source, names in members.items() if names}
    return {**groups, **kinetix_groups(table)}


class Scored(NamedTuple):
    """A policy's scores: per level, and per group (`group_means`)."""

    table: Table
    groups: dict[str, float]

    @property
    def mean(self) -> float:
        """Mean solve rate over every level."""
        return float(np.mean([s["solve_rate"] for s in self.table.values()])) if self.table else float("nan")


def evaluating_phase(levels: int, attempts: int, scored: int | None = None) -> str:
    """How an evaluation's phase is named wherever it is shown (the trainers' progress, the evaluator's status):
    "evaluating 42 levels x 20 attempts", or with `scored`, how many of them are scored so far, first, so that a
    narrow display keeps it: "evaluating 16/42 levels x 20 attempts"."""
    counted = f"{levels}" if scored is None else f"{scored}/{levels}"
    return f"evaluating {counted} level{'s' if levels != 1 else ''} x {attempts} attempt{'s' if attempts != 1 else ''}"


LevelScored = Callable[[int, int, str, float], None]
"""`on_level(done, total, name, solve_rate)`: told of each level's score as it is known."""


def score_policy(agent: Agent, params: Any, env_params: EnvParams, sets: LevelSets, key: jax.Array, attempts: int,
                 greedy: bool = False, on_level: LevelScored | None = None,
                 chunk_levels: int | None = None) -> Scored:
    """`params` played `attempts` times on every level of `sets` (Kinetix's protocol). `on_level` is told of each
    level's solve rate as it is known.

    Without `chunk_levels` all the levels are played in one program, so they are known together, when it ends (a
    caller shows the wait before it as a phase). With it, they are played that many at a time, so that a long
    evaluation shows how far it is: every chunk runs the same program (the last one is filled up by repeating its
    last level, whose extra scores are dropped), with a key of its own (`jax.random.fold_in(key, chunk)`), and
    `on_level` hears a chunk's levels when it ends. The random draws differ from the unchunked evaluation's, the
    protocol does not."""
    total = len(sets.names)
    size = total if chunk_levels is None else max(1, min(chunk_levels, total))
    table: Table = {}
    for chunk, start in enumerate(range(0, total, size)):
        count = min(size, total - start)
        if size == total:
            levels, chunk_key = sets.levels, key
        else:
            rows = np.minimum(np.arange(start, start + size), total - 1)
            levels, chunk_key = jax.tree.map(lambda x, rows=rows: x[rows], sets.levels), jax.random.fold_in(key, chunk)
        scores = evaluate(agent, params, env_params, levels, chunk_key, attempts=attempts, greedy=greedy)
        part = scores_table(sets.names[start:start + count], LevelScores(*(x[:count] for x in scores)))
        if on_level is not None:
            for done, (name, row) in enumerate(part.items(), start=len(table) + 1):
                on_level(done, total, name, row["solve_rate"])
        table.update(part)
    return Scored(table, group_means(table, sets.members))


def evaluation_columns(table: Table, groups: dict[str, float], policy_version: int) -> dict[str, float]:
    """The metrics.jsonl columns of one evaluation, the same in both modes: `eval/policy_version`, `eval/mean`,
    `eval/<group>` and `eval/level/<level>` (solve rates)."""
    rates = [s["solve_rate"] for s in table.values()]
    columns = {f"{COLUMN}/policy_version": float(policy_version),
               f"{COLUMN}/mean": float(np.mean(rates)) if rates else float("nan")}
    columns.update({f"{COLUMN}/{group}": rate for group, rate in groups.items()})
    columns.update({f"{COLUMN}/level/{name}": s["solve_rate"] for name, s in table.items()})
    return columns


def format_scores(table: Table, groups: dict[str, float] | None = None) -> str:
    """A terminal table of per-level scores, their mean, and the group means (Kinetix's groups by default)."""
    width = max([len(n) for n in table] + [5])
    lines = [f"{'level':<{width}}  solved  return  length"]
    for name, s in table.items():
        lines.append(f"{name:<{width}}  {s['solve_rate']:>6.0%}  {s['mean_return']:>6.3f}  {s['mean_length']:>6.1f}")
    if table:
        mean = np.mean([s["solve_rate"] for s in table.values()])
        lines.append(f"{'mean':<{width}}  {mean:>6.0%}")
    for group, rate in (kinetix_groups(table) if groups is None else groups).items():
        lines.append(f"{group:<{width}}  {rate:>6.0%}")
    return "\n".join(lines)
