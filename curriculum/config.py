"""The curriculum's configuration: which algorithm, the buffer's fixed sizes, and the knobs a person may retune
while a run goes on.

Defaults follow Kinetix's PLR/ACCEL setup (MaxMC, rank prioritisation at temperature 1, staleness 0.3, replay
probability 0.5, minimum fill 0.5, vanilla PLR) and its SFL setup (half the batch from the buffer), scaled to a
buffer that fits a small run. Fields split in two: the static ones fix array shapes and the algorithm, so they
hold for the life of a run; the live knobs (`LIVE_KNOBS`) are arrays in the curriculum state, so changing one
takes effect at the next sample without recompiling anything, and it is checkpointed with the buffer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

Method = Literal["dr", "plr", "accel", "sfl"]
SflScoring = Literal["online", "batch"]
ScoreFunction = Literal["maxmc", "pvl", "l1_value_loss", "learnability"]
Prioritization = Literal["rank", "power"]

METHODS: tuple[str, ...] = ("dr", "plr", "accel", "sfl")
"""The method names, as `curriculum.methods.METHODS` registers them (that package imports this module, so the
names are repeated here; a test keeps the two alike)."""
SCORE_FUNCTIONS: tuple[str, ...] = ("maxmc", "pvl", "l1_value_loss", "learnability")
PRIORITIZATIONS: tuple[str, ...] = ("rank", "power")
SFL_SCORINGS: tuple[str, ...] = ("online", "batch")

LIVE_KNOBS: tuple[str, ...] = (
    "score",
    "prioritization",
    "temperature",
    "staleness_coef",
    "replay_prob",
    "min_fill",
    "robust",
    "num_edits",
    "sfl_ratio",
    "candidate_episodes",
    "score_memory",
)
"""Fields `impulse curriculum set` may change on a live service; every other field is fixed for the run."""


@dataclass(frozen=True)
class CurriculumConfig:
    """Which levels the agent trains on. `method="dr"` is domain randomisation (fresh random levels every batch);
    the others keep a level buffer. A command-line `curriculum=sfl` is short for `curriculum.method=sfl`."""

    SHORTHAND: ClassVar[str] = "method"

    method: Method = "dr"
    """"dr": fresh random levels; "plr": prioritised level replay (robust PLR with `robust`); "accel": PLR whose
    replayed levels are mutated into new candidates; "sfl": sampling for learnability."""
    buffer_size: int = 512
    """Levels the buffer holds (Kinetix: 4,000 for PLR/ACCEL, 1,024 for SFL)."""
    staging_factor: int = 2
    """New and mutated candidates wait in a staging area of staging_factor x batch size slots until they have
    finished `candidate_episodes` episodes and are scored; at least 2, so a batch of fresh candidates never
    overwrites the candidates handed out with it."""
    max_edits: int = 8
    """The largest `num_edits` a live change may ask for (the mutation loop's static length)."""
    noop_filter: bool = True
    """New random levels pass Kinetix's soft no-op filter (levels doing nothing solves are rarely kept)."""
    filter_ratio: int = 2
    """No-op filter: candidates generated per level kept."""
    filter_steps: int = 64
    """No-op filter: env steps of the all-zero policy per candidate."""
    levels_ahead: int = 8
    """The curriculum service only: batches of filtered new levels it keeps ready, made on a thread of their own so
    that a level request never waits for the no-op filter's simulation. When requests outrun that thread and none
    is ready, a new batch is drawn unfiltered at once and counted (`unfiltered` in the service's status). 0: every
    new batch is filtered on the request path, as in fused training, and requests wait for it."""
    sfl_scoring: SflScoring = "online"
    """SFL: how levels are scored for learnability. "online": from the episodes the agent trains on (a candidate
    after `candidate_episodes` episodes, a buffered level whenever it is replayed), replaying once the buffer is
    `min_fill` full; "batch": Kinetix's form, in which every `sfl_refresh_updates` updates (and before the first)
    `sfl_candidates` fresh levels are each played `sfl_attempts` times by the current policy, the buffer becomes
    the most learnable of them, and replay starts at the first update. In a distributed run the curriculum service
    follows the learner's weights to score (policy versions stand for updates), on a thread of its own."""
    sfl_candidates: int = 1024
    """SFL batch scoring: fresh levels scored at each refresh (Kinetix: 3 x 4,096)."""
    sfl_score_block: int = 1024
    """SFL batch scoring in the curriculum service: candidates played per call. A scoring of more candidates runs
    as equal blocks of this many, one after another, so that a long scoring (a first fill of thousands of L levels
    on a CPU takes most of an hour) counts its progress on the status line and holds one block's environments in
    memory at a time; it must divide `sfl_candidates` when smaller. On a GPU, a block of every candidate (one call)
    keeps the device busiest. Fused training scores inside its step and ignores it."""
    sfl_attempts: int = 4
    """SFL batch scoring: episodes per candidate from its start (stochastic policy); its solve rate p gives the
    learnability p (1 - p)."""
    sfl_refresh_updates: int = 32
    """SFL batch scoring: updates between refreshes of the buffer (Kinetix: 128)."""
    sfl_hold_while_scoring: bool = False
    """SFL batch scoring in the curriculum service: refuse level requests during every scoring, not only the
    first, so actors (and with them the learner) wait as the fused trainer does and no batch comes from a buffer
    more than one refresh old. For a service that shares its device with actors or the learner, whose scorings
    would otherwise run slowly and late; it costs the actors' time while a scoring runs."""
    devices: tuple[int, ...] = ()
    """The GPU the curriculum service runs on, as a one-item list of its position among the GPUs the process may
    see (it then sees only that one); empty: every GPU is visible and JAX uses the first. Fused training ignores
    it (the curriculum runs inside the training step)."""

    # Live knobs (LIVE_KNOBS).
    score: ScoreFunction = "maxmc"
    """PLR/ACCEL score: "maxmc" (best return ever seen minus the mean value), "pvl" (mean positive GAE),
    "l1_value_loss" (mean absolute GAE) or "learnability" (p(1 - p) from the solve rate p). SFL always scores by
    learnability."""
    prioritization: Prioritization = "rank"
    """Replay weights from scores: "rank" (1 / rank) or "power" (the score itself, clipped at 0), each raised to
    1 / temperature."""
    temperature: float = 1.0
    """Replay weights are raised to 1 / temperature: above 1 flattens the distribution, below 1 sharpens it."""
    staleness_coef: float = 0.3
    """Share of the replay distribution given to levels by how long ago they were last sampled."""
    replay_prob: float = 0.5
    """PLR/ACCEL: probability that a batch is replayed from the buffer (once it is `min_fill` full)."""
    min_fill: float = 0.5
    """Fraction of the buffer that must be filled before any level is replayed (PLR, ACCEL and SFL)."""
    robust: bool = False
    """Robust PLR: new and mutated levels are only evaluated, never trained on (their steps are masked out of the
    PPO update); gradients come from replayed levels alone."""
    num_edits: int = 3
    """ACCEL: edits per mutated child (Kinetix paper: 3; its repository: 5)."""
    sfl_ratio: float = 0.5
    """SFL: fraction of every batch drawn (uniformly) from the buffer; the rest are fresh candidates."""
    candidate_episodes: int | None = None
    """Finished episodes a new candidate needs before it is scored and offered to the buffer; a candidate that has
    fewer is handed out again in later batches. None: the method's default (its `default_candidate_episodes`): 4
    for SFL (a solve rate needs several episodes), 1 for PLR and ACCEL (Kinetix scores a level from the episodes of
    one rollout)."""
    score_memory: float = 0.9
    """Solve counts of buffered levels decay by this factor at every new result (1 keeps all history, 0 only
    the newest window); their learnability follows the current policy rather than its history."""

    def __post_init__(self) -> None:
        problems = knob_problems(self)
        if len(self.devices) > 1 or any(isinstance(d, bool) or not isinstance(d, int) or d < 0 for d in self.devices):
            problems.append(f"curriculum.devices must be empty or one device number >= 0, got {list(self.devices)}")
        if self.buffer_size < 1:
            problems.append(f"curriculum.buffer_size must be >= 1, got {self.buffer_size}")
        if self.staging_factor < 2:
            problems.append(f"curriculum.staging_factor must be >= 2, got {self.staging_factor}")
        if self.max_edits < 0:
            problems.append(f"curriculum.max_edits must be >= 0, got {self.max_edits}")
        if self.sfl_scoring not in SFL_SCORINGS:
            problems.append(f"curriculum.sfl_scoring must be one of {', '.join(SFL_SCORINGS)}, got "
                            f"{self.sfl_scoring!r}")
        for name in ("sfl_candidates", "sfl_attempts", "sfl_refresh_updates", "sfl_score_block"):
            if getattr(self, name) < 1:
                problems.append(f"curriculum.{name} must be >= 1, got {getattr(self, name)}")
        if 1 <= self.sfl_score_block < self.sfl_candidates and self.sfl_candidates % self.sfl_score_block:
            problems.append(f"curriculum.sfl_score_block must divide curriculum.sfl_candidates "
                            f"({self.sfl_candidates}) when smaller, got {self.sfl_score_block}")
        if self.levels_ahead < 0:
            problems.append(f"curriculum.levels_ahead must be >= 0, got {self.levels_ahead}")
        for name in ("filter_ratio", "filter_steps"):
            if getattr(self, name) < 1:
                problems.append(f"curriculum.{name} must be >= 1, got {getattr(self, name)}")
        if problems:
            raise ValueError("; ".join(problems))


def knob_problems(config: CurriculumConfig) -> list[str]:
    """What is wrong with the live knobs' values, one sentence each (empty when they are fine)."""
    problems = []
    for name in ("replay_prob", "min_fill", "staleness_coef", "sfl_ratio", "score_memory"):
        value = getattr(config, name)
        if not 0.0 <= value <= 1.0:
            problems.append(f"curriculum.{name} must be in [0, 1], got {value}")
    if not config.temperature > 0.0:
        problems.append(f"curriculum.temperature must be > 0, got {config.temperature}")
    if not 0 <= config.num_edits <= config.max_edits:
        problems.append(f"curriculum.num_edits must be in [0, max_edits={config.max_edits}], got {config.num_edits}")
    if config.candidate_episodes is not None and config.candidate_episodes < 1:
        problems.append(f"curriculum.candidate_episodes must be >= 1, got {config.candidate_episodes}")
    return problems
