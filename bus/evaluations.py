"""Evaluation frames: an evaluator's scores of one learner policy on its level sets, to the learner (which writes
them to metrics.jsonl) and to whoever watches (`evaluator/results/<id>`).

An evaluation names the policy it scored by the header's (learner epoch, policy version) and carries, in its meta,
the solve rate of every level (`levels`: name -> {"solve_rate", "mean_return", "mean_length"}) and of every group
(`groups`: name -> mean solve rate: each level set, Kinetix's "<size>_all" and "<size>_<prefix>" groups), and how
many newer policies the evaluator skipped while it scored this one. A control frame: it carries a digest.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any, NamedTuple

from impulse.bus.codec import Kind, Rejected, decode, encode
from impulse.bus.stamp import Stamp

LEVELS = "levels"
GROUPS = "groups"
SKIPPED = "skipped"
SCORES = ("solve_rate", "mean_return", "mean_length")
MAX_LEVELS = 4096
"""More levels than any set holds: a frame naming more is refused rather than written to every metrics row."""


class Evaluation(NamedTuple):
    """The scores of the policy (learner_epoch, policy_version) on the evaluator's level sets."""

    learner_epoch: int
    policy_version: int
    levels: dict[str, dict[str, float]]
    groups: dict[str, float]
    skipped: int
    """Newer policies the evaluator did not score while it scored this one (it always scores the newest)."""


def encode_evaluation(stamp: Stamp, levels: Mapping[str, Mapping[str, float]], groups: Mapping[str, float],
                      skipped: int = 0) -> bytearray:
    """The scores of the stamp's policy (epoch and version) as an evaluation frame."""
    meta: dict[str, Any] = {LEVELS: {name: {k: float(v) for k, v in scores.items()} for name, scores in levels.items()},
                            GROUPS: {name: float(rate) for name, rate in groups.items()}, SKIPPED: int(skipped)}
    return encode(Kind.EVALUATION, {}, run=stamp.run, policy_version=stamp.policy_version,
                  learner_epoch=stamp.epoch, seq=stamp.next_seq(Kind.EVALUATION), meta=meta)


def _number(value: object) -> bool:
    return type(value) in (int, float) and math.isfinite(value)


def decode_evaluation(payload: bytes, run: str) -> Evaluation:
    """The evaluation a frame carries; raises `bus.codec.Rejected` unless every level and group has finite
    numbers (solve rates within [0, 1]) and the counts are plausible."""
    message = decode(payload, run=run, kinds=Kind.EVALUATION)
    levels, groups, skipped = message.meta.get(LEVELS), message.meta.get(GROUPS), message.meta.get(SKIPPED, 0)
    if not isinstance(levels, dict) or not isinstance(groups, dict) or type(skipped) is not int or skipped < 0:
        raise Rejected("schema", "an evaluation without levels, groups or a skipped count")
    if len(levels) > MAX_LEVELS or len(groups) > MAX_LEVELS:
        raise Rejected("schema", f"an evaluation of more than {MAX_LEVELS} levels or groups")
    for name, scores in levels.items():
        if not isinstance(scores, dict) or set(scores) != set(SCORES) or not all(map(_number, scores.values())):
            raise Rejected("schema", f"level {name[:60]!r} has no finite {', '.join(SCORES)}")
        if not 0.0 <= scores["solve_rate"] <= 1.0:
            raise Rejected("schema", f"level {name[:60]!r} has a solve rate outside [0, 1]")
    if not all(_number(rate) and 0.0 <= rate <= 1.0 for rate in groups.values()):
        raise Rejected("schema", "a group's solve rate is not a number in [0, 1]")
    return Evaluation(message.learner_epoch, message.policy_version, levels, groups, skipped)
