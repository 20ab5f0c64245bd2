"""The curriculum methods, one module each behind the protocol of `curriculum.methods.base.Curriculum`:

- `dr`: domain randomisation, fresh random levels every batch;
- `plr`: prioritised level replay, and robust PLR under the live `robust` knob;
- `accel`: PLR whose replayed levels are mutated into new candidates;
- `sfl`: sampling for learnability, scored online from training or in batches by the caller's policy.

They share the staging area (`curriculum.staging`), the scores, replay distribution and eviction
(`curriculum.priority`), and the row-by-row application of results (`curriculum.methods.apply`).
`make_curriculum` builds the one a config names; callers hold it as a `Curriculum` and never ask which it is.
"""

from __future__ import annotations

from impulse.curriculum.config import CurriculumConfig
from impulse.curriculum.methods.accel import ACCEL
from impulse.curriculum.methods.base import Curriculum
from impulse.curriculum.methods.dr import DomainRandomisation
from impulse.curriculum.methods.plr import PLR
from impulse.curriculum.methods.sfl import SFL
from impulse.engine.env.spec import EnvParams, EnvSpec
from impulse.engine.levels.generator import GeneratorConfig

METHODS: dict[str, type[Curriculum]] = {cls.method: cls for cls in (DomainRandomisation, PLR, ACCEL, SFL)}
"""Every method by its name (`curriculum.method`). `curriculum.config.METHODS`, which the config cannot take from
here (this package imports the config), lists the same names; a test keeps the two alike."""

__all__ = ["ACCEL", "METHODS", "PLR", "SFL", "Curriculum", "DomainRandomisation", "make_curriculum"]


def make_curriculum(config: CurriculumConfig, spec: EnvSpec, env_params: EnvParams, batch_size: int,
                    generator: GeneratorConfig | None = None) -> Curriculum:
    """The curriculum `config.method` names, handing out batches of `batch_size` levels of `spec`'s sizes, new
    levels drawn by `generator` (None: the default generator)."""
    method = METHODS[config.method]
    return method(config, spec, env_params, batch_size, GeneratorConfig() if generator is None else generator)
