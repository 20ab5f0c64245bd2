"""Why a level can never be solved, as warnings for the editor and for Save (which still saves: a level being built
may lack its goal for a while).

The check is the engine's (`engine.levels.checks.unsolvable_reasons`, which `impulse levels validate` uses too:
no green shape, no blue shape, no green and blue pair that can ever touch, every such pair fixed in place and
apart), so the studio and the command line warn alike; the studio words the reasons as one sentence for the page.
"""

from __future__ import annotations

from impulse.engine.levels.checks import unsolvable_reasons as engine_unsolvable_reasons
from impulse.engine.levels.level import Level
from impulse.engine.physics.sizes import SceneSizes

PREFIX = "this level cannot be solved: "


def unsolvable_reasons(level: Level, sizes: SceneSizes) -> list[str]:
    """The page's warnings for `level` (one level of `sizes`): one sentence, "this level cannot be solved: <the
    engine's reasons, joined by "; ">", or none when the engine's check finds no reason (which does not prove the
    level solvable)."""
    reasons = engine_unsolvable_reasons(level, sizes)
    return [PREFIX + "; ".join(reasons)] if reasons else []
