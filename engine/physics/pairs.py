"""Static tables of which bodies can touch, and the order in which the solver visits their contacts.

Everything here is plain numpy computed once per `SceneSizes` and baked into the compiled step as constants.

Pair order (Jax2D's, so that level files' contact caches line up): polygon-polygon pairs (i < j, row-major,
without arena-arena pairs), then circle-polygon pairs (circle-major; body a is the circle), then circle-circle
pairs. A polygon pair has two contact points, other pairs one. Contact slots are: point 0 of every
polygon-polygon pair, point 1 of every polygon-polygon pair, the circle-polygon contacts, the circle-circle
contacts.

Solver schedule: contacts are split into phases in which no body appears twice, so a phase's contacts can be
solved in parallel with plain (unique-index) reads and writes and the whole sweep is still Gauss-Seidel. Jax2D
instead sorts contacts into padded batches of 16 every iteration and solves each batch Jacobi-style.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from impulse.engine.physics.sizes import SceneSizes


@dataclass(frozen=True)
class PairTables:
    num_rr: int
    num_cr: int
    num_cc: int
    rr_a: np.ndarray  # polygon index (= body index)
    rr_b: np.ndarray
    cr_circle: np.ndarray  # circle index (body index minus P)
    cr_polygon: np.ndarray  # polygon index
    cc_a: np.ndarray  # circle indices
    cc_b: np.ndarray
    pair_a: np.ndarray  # [num_pairs] body index of side a
    pair_b: np.ndarray
    contact_a: np.ndarray  # [K] body index of side a of each contact slot
    contact_b: np.ndarray
    contact_pair: np.ndarray  # [K] pair index of each contact slot
    phases: tuple[np.ndarray, ...]  # contact slot indices, solved in this order

    @property
    def num_pairs(self) -> int:
        return self.num_rr + self.num_cr + self.num_cc

    @property
    def num_contacts(self) -> int:
        return 2 * self.num_rr + self.num_cr + self.num_cc


def _schedule(contact_a: np.ndarray, contact_b: np.ndarray, num_rr: int) -> tuple[np.ndarray, ...]:
    """Greedy colouring of contacts so that no body appears twice in a phase.

    A polygon pair's point 1 is kept in a later phase than its point 0, so each pair is visited in Jax2D's
    point order.
    """
    phase_bodies: list[set[int]] = []
    phase_members: list[list[int]] = []
    phase_of = np.zeros(len(contact_a), dtype=np.int64)
    order = []
    for pair in range(num_rr):
        order += [pair, num_rr + pair]
    order += list(range(2 * num_rr, len(contact_a)))
    for k in order:
        a, b = int(contact_a[k]), int(contact_b[k])
        first = phase_of[k - num_rr] + 1 if num_rr <= k < 2 * num_rr else 0
        p = first
        while p < len(phase_bodies) and (a in phase_bodies[p] or b in phase_bodies[p]):
            p += 1
        if p == len(phase_bodies):
            phase_bodies.append(set())
            phase_members.append([])
        phase_bodies[p].update((a, b))
        phase_members[p].append(k)
        phase_of[k] = p
    return tuple(np.asarray(sorted(m), dtype=np.int32) for m in phase_members)


@functools.cache
def pair_tables(sizes: SceneSizes) -> PairTables:
    P, C, S = sizes.num_polygons, sizes.num_circles, sizes.num_static_polygons
    rr = [(i, j) for i in range(P) for j in range(i + 1, P) if not (i < S and j < S)]
    cr = [(c, p) for c in range(C) for p in range(P)]
    cc = [(i, j) for i in range(C) for j in range(i + 1, C)]
    as_array = functools.partial(np.asarray, dtype=np.int32)
    rr_a = as_array([i for i, _ in rr]).reshape(-1)
    rr_b = as_array([j for _, j in rr]).reshape(-1)
    cr_circle = as_array([c for c, _ in cr]).reshape(-1)
    cr_polygon = as_array([p for _, p in cr]).reshape(-1)
    cc_a = as_array([i for i, _ in cc]).reshape(-1)
    cc_b = as_array([j for _, j in cc]).reshape(-1)
    pair_a = np.concatenate([rr_a, cr_circle + P, cc_a + P]).astype(np.int32)
    pair_b = np.concatenate([rr_b, cr_polygon, cc_b + P]).astype(np.int32)
    n_rr = len(rr)
    contact_pair = np.concatenate(
        [np.arange(n_rr), np.arange(n_rr), np.arange(n_rr, len(pair_a))]
    ).astype(np.int32)
    contact_a, contact_b = pair_a[contact_pair], pair_b[contact_pair]
    return PairTables(
        num_rr=n_rr,
        num_cr=len(cr),
        num_cc=len(cc),
        rr_a=rr_a,
        rr_b=rr_b,
        cr_circle=cr_circle,
        cr_polygon=cr_polygon,
        cc_a=cc_a,
        cc_b=cc_b,
        pair_a=pair_a,
        pair_b=pair_b,
        contact_a=contact_a,
        contact_b=contact_b,
        contact_pair=contact_pair,
        phases=_schedule(contact_a, contact_b, n_rr),
    )
