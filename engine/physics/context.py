"""What the solver stages of one step share: the step's constants and its static sizes and options.

The step computes its per-contact and per-joint constants once (stage 2) and every later stage only reads them.
`StepContext` carries them together, so a stage takes (what it changes, the context) instead of a long list of
arguments, and the schedules (phased, Jax2D's batches, the fused kernel) read the same names.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple

import jax

from impulse.engine.physics.contact_solver import ContactRows
from impulse.engine.physics.joint_solver import JointRows
from impulse.engine.physics.narrowphase import Contacts
from impulse.engine.physics.options import SolverOptions
from impulse.engine.physics.pairs import PairTables, pair_tables
from impulse.engine.physics.params import SimParams
from impulse.engine.physics.sizes import SceneSizes
from impulse.engine.physics.state import Joints

Array = jax.Array


class Impulses(NamedTuple):
    """Accumulated contact impulses, one entry per contact slot (or per slot of one phase)."""

    normal: Array
    tangent: Array


@jax.tree_util.register_dataclass
@dataclass(frozen=True)
class StepContext:
    """The constants of one step's solver stages (traced) with the scene's sizes and solver options (static).

    A pytree: the arrays are its leaves and `sizes` and `options` its static part, so it can be handed to
    `jax.lax.platform_dependent` and closed over by loops like any tree of arrays.
    """

    params: SimParams
    joints: Joints
    """The scene's joints as the step began (limits, fixed flags, last step's accumulators)."""
    joint_rows: JointRows
    contacts: Contacts
    """Detection of every contact slot: points, normals, depths, touching flags."""
    contact_rows: ContactRows
    enabled: Array
    """[K] bool: contact slots that may exchange impulses this step."""
    sizes: SceneSizes = field(metadata={"static": True})
    options: SolverOptions = field(metadata={"static": True})

    @property
    def tables(self) -> PairTables:
        """The static pair and contact-slot tables of `sizes`."""
        return pair_tables(self.sizes)
