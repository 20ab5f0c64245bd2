"""The layout of the curriculum's messages on the bus: level results (actors to the curriculum) and level batches
(the curriculum's answer to an actor's `levels/sample` query), as named arrays, and the schemas that check them.

The frames themselves are `bus.levels`'s; the arrays are checked against the schemas here before they reach a
jitted function, so a malformed or foreign message is refused with a reason instead of crashing the service or
making it recompile.
"""

from __future__ import annotations

import jax
import numpy as np

from impulse.bus.codec import Kind, Message, Rejected
from impulse.bus.schema import ArraySpec, Schema, check
from impulse.curriculum.results import LevelResults, results_from_host, results_to_host
from impulse.curriculum.state import LevelBatch
from impulse.engine.levels.generator import sample_random_level
from impulse.engine.levels.level import LEVEL_ID_WORDS
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.pytree import tree_arrays, tree_from_arrays

_PER_LEVEL = ("K",)

LEVEL_RESULTS_SCHEMA = Schema(
    Kind.LEVEL_RESULTS,
    {
        "level_id": ArraySpec(np.dtype(np.uint32), ("K", LEVEL_ID_WORDS)),
        "episodes": ArraySpec(np.dtype(np.int32), _PER_LEVEL),
        "solved": ArraySpec(np.dtype(np.int32), _PER_LEVEL),
        "return_sum": ArraySpec(np.dtype(np.float32), _PER_LEVEL, finite=True),
        "return_max": ArraySpec(np.dtype(np.float32), _PER_LEVEL, finite=True),
        "value_sum": ArraySpec(np.dtype(np.float32), _PER_LEVEL, finite=True),
        "pvl_sum": ArraySpec(np.dtype(np.float32), _PER_LEVEL, finite=True),
        "l1_sum": ArraySpec(np.dtype(np.float32), _PER_LEVEL, finite=True),
        "policy_version": ArraySpec(np.dtype(np.int32), _PER_LEVEL),
    },
)


def results_arrays(results: LevelResults) -> dict[str, np.ndarray]:
    """The valid rows of `results` as the arrays of a LEVEL_RESULTS frame."""
    return results_to_host(results)


class ResultsError(ValueError):
    """Level results that are well-formed arrays but make no sense (negative counts, more solved than played)."""


def checked_results(message: Message) -> dict[str, np.ndarray]:
    """The results a frame carries, as host arrays; raises `bus.codec.Rejected` for a frame that does not fit the
    schema and `ResultsError` for impossible counts."""
    check(message, LEVEL_RESULTS_SCHEMA)
    arrays = {name: np.asarray(message.arrays[name]) for name in LEVEL_RESULTS_SCHEMA.arrays}
    episodes, solved = arrays["episodes"], arrays["solved"]
    if (episodes < 0).any() or (solved < 0).any() or (solved > episodes).any():
        raise ResultsError("episode counts must satisfy 0 <= solved <= episodes")
    if (arrays["level_id"] == 0).all(axis=-1).any():
        raise ResultsError("level id 0 (unassigned) in results")
    return arrays


def results_chunks(results: list[dict[str, np.ndarray]], rows: int) -> list[LevelResults]:
    """`checked_results` of several frames, in their order, packed into as few chunks of `rows` rows as they fit
    in (the curriculum's `update` costs the same for a full chunk as for a nearly empty one)."""
    if not results:
        return []
    arrays = {name: np.concatenate([got[name] for got in results]) for name in LEVEL_RESULTS_SCHEMA.arrays}
    count = arrays["episodes"].shape[0]
    return [results_from_host({name: a[start:start + rows] for name, a in arrays.items()}, rows)
            for start in range(0, count, rows)]


def results_from_message(message: Message, rows: int) -> list[LevelResults]:
    """The results a frame carries, in chunks of `rows` rows (see `checked_results` for what it raises)."""
    return results_chunks([checked_results(message)], rows)


def level_batch_template(sizes: SceneSizes, batch_size: int) -> LevelBatch:
    """The shapes and dtypes of a batch of `batch_size` levels of `sizes` (nothing is computed)."""
    levels = jax.eval_shape(jax.vmap(lambda k: sample_random_level(k, sizes)),
                            jax.random.split(jax.random.PRNGKey(0), batch_size))
    return LevelBatch(levels, jax.ShapeDtypeStruct((batch_size,), np.dtype(bool)),
                      jax.ShapeDtypeStruct((batch_size,), np.dtype(np.int32)))


def level_batch_schema(template: LevelBatch) -> Schema:
    """Exactly the batch an actor's rollout was compiled for (B levels of its size), with finite scenes."""
    example = jax.tree.map(lambda leaf: np.zeros(leaf.shape, leaf.dtype), template)
    return Schema.from_example(Kind.LEVELS, tree_arrays(example), finite=True)


def level_batch_arrays(batch: LevelBatch) -> dict[str, np.ndarray]:
    return tree_arrays(batch)


def level_batch_from_message(message: Message, schema: Schema, template: LevelBatch) -> LevelBatch:
    """The batch a LEVELS frame carries, after the schema check (raises `bus.codec.Rejected` if it fails)."""
    check(message, schema)
    return tree_from_arrays(message.arrays, template)


def played_levels_schema(sizes: SceneSizes) -> Schema:
    """Any number K of levels of `sizes`, with finite scenes: the batch an actor says it plays next
    (`actor/played/<actor>`, heard by a recorder), whose K depends on the actor's level source."""
    example = jax.tree.map(lambda leaf: np.zeros(leaf.shape, leaf.dtype), level_batch_template(sizes, 1))
    return Schema.from_example(Kind.LEVELS, tree_arrays(example), leading=("K",), finite=True)


def played_levels_from_message(message: Message, schema: Schema, max_levels: int) -> dict[str, np.ndarray]:
    """The levels of a played-levels frame as named leaves ([K, ...], named as `tree_arrays` names a `Level`),
    after the schema check; raises `bus.codec.Rejected` if it fails or K exceeds `max_levels`."""
    dims = check(message, schema)
    if dims.get("K", 0) > max_levels:
        raise Rejected("bad_shape", f"{dims['K']} levels in one batch, more than the {max_levels} expected")
    prefix = "levels/"
    return {name[len(prefix):]: array for name, array in message.arrays.items() if name.startswith(prefix)}
