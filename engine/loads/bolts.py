"""Rock bolts and cables (issue 16): an axial and a shear spring between a point of one block
(the head) and a point of another block or of the ground (the anchor).

Axial force (tension positive) `N = T0 + k_a (L − L0 − p)` with `L` the current length,
`L0` the installed one, `T0` the pretension and `p` the plastic elongation; `|N|` is capped
at the capacity (the excess becomes plastic elongation). The shear force `S` (perpendicular
to the bolt) grows by `k_s` times the ends' relative transverse displacement, capped at the
shear capacity. A bolt whose ends have moved apart by more than its rupture displacement
since installation breaks and stops acting.

In a step the bolt is Shi's point spring between its two ends (docs/theory.md "Fixed point",
with the two-point coupling of a contact spring, paper eqs. 24 and 29):
`P = k_a e eᵀ + k_s (I − e eᵀ)` along the current axis `e`, stiffness `Tᵀ P T` on the
blocks' matrices, and the force at the step's start (pretension included) as point loads
`T_iᵀ f`, `−T_jᵀ f`. A capped component carries no stiffness in the step. Energy: the
bolt stores `T0 x + ½ k_a x² + |S|² / (2 k_s)` (x the elastic elongation); the work the
blocks do on it beyond that (implicit spring, yield, rupture) counts as dissipation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.geometry.transforms import displacement_matrices

#: bolt states recorded per step
ELASTIC, YIELDED, BROKEN = 0, 1, 2  # YIELDED: has reached a capacity (and stays so)
STATUS_NAMES = {ELASTIC: "elastic", YIELDED: "yielded", BROKEN: "broken"}
#: a force within this fraction of its capacity is at the capacity (carries no stiffness)
_AT_CAPACITY = 1e-9


@dataclass(frozen=True)
class Bolt:
    """A rock bolt or cable from `head (3,)` m on block `block` to `anchor (3,)` m on block
    `anchor_block` (-1: the ground, a point that never moves).

    Axial and shear stiffness (N/m), pretension (N, tension), axial `capacity` (N, the
    yield force; inf: none), `shear_capacity` (N; None: the axial capacity) and
    `rupture_displacement` (m: the bolt breaks when its ends have moved apart by more since
    installation; inf: never). See :mod:`engine.loads.bolts`.
    """

    block: int
    head: np.ndarray
    anchor: np.ndarray
    anchor_block: int = -1
    axial_stiffness: float = 1e8
    shear_stiffness: float = 0.0
    pretension: float = 0.0
    capacity: float = float("inf")
    shear_capacity: float | None = None
    rupture_displacement: float = float("inf")
    name: str = ""
    #: installed mid-run (a stage): the length (m) and the anchor-minus-head vector (m)
    #: the bolt had when installed, unstressed but for its pretension (None: at t = 0)
    installed_length: float | None = None
    installed_span: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class BoltSet:
    """The bolts of a run as arrays (b bolts): head block, anchor block (-1: ground), ends
    at installation `(b, 3)` m, installed length `(b,)` m, stiffnesses N/m, pretension N,
    capacities N, rupture displacements m (inf: none); `span0 (b, 3)` m the anchor minus the
    head at installation (the rupture displacement counts from it)."""

    bolts: tuple[Bolt, ...]
    block: np.ndarray
    anchor_block: np.ndarray
    head0: np.ndarray
    anchor0: np.ndarray
    length0: np.ndarray
    axial_stiffness: np.ndarray
    shear_stiffness: np.ndarray
    pretension: np.ndarray
    capacity: np.ndarray
    shear_capacity: np.ndarray
    rupture: np.ndarray
    span0: np.ndarray

    def __len__(self) -> int:
        return len(self.bolts)


def bolt_set(bolts: list[Bolt] | tuple[Bolt, ...]) -> BoltSet:
    """The :class:`BoltSet` of the model's bolts."""
    head = np.array([b.head for b in bolts], float).reshape(-1, 3)
    anchor = np.array([b.anchor for b in bolts], float).reshape(-1, 3)
    cap = np.array([b.capacity for b in bolts], float)
    length = np.linalg.norm(anchor - head, axis=1)
    for k, b in enumerate(bolts):
        if not (0 <= b.pretension <= b.capacity and b.axial_stiffness >= 0
                and b.shear_stiffness >= 0 and b.rupture_displacement > 0):
            raise ValueError(f"bolt {b.name or k}: needs 0 <= pretension <= capacity, "
                             "stiffnesses >= 0 and a positive rupture displacement")
    return BoltSet(
        bolts=tuple(bolts), block=np.array([b.block for b in bolts], dtype=np.int64),
        anchor_block=np.array([b.anchor_block for b in bolts], dtype=np.int64),
        head0=head, anchor0=anchor,
        length0=np.array([length[k] if b.installed_length is None else b.installed_length
                          for k, b in enumerate(bolts)], float),
        axial_stiffness=np.array([b.axial_stiffness for b in bolts], float),
        shear_stiffness=np.array([b.shear_stiffness for b in bolts], float),
        pretension=np.array([b.pretension for b in bolts], float), capacity=cap,
        shear_capacity=np.array([cap[k] if b.shear_capacity is None else b.shear_capacity
                                 for k, b in enumerate(bolts)], float),
        rupture=np.array([b.rupture_displacement for b in bolts], float),
        span0=np.array([anchor[k] - head[k] if b.installed_span is None else b.installed_span
                        for k, b in enumerate(bolts)], float).reshape(-1, 3))


def _point(centroid: np.ndarray, affine: np.ndarray, c0: np.ndarray, b: int,
           p0: np.ndarray) -> np.ndarray:
    """Current position of the material point of block `b` that started at `p0`."""
    return centroid[b] + affine[b] @ (p0 - c0[b])


def bolt_ends(bs: BoltSet, c0: np.ndarray, centroid: np.ndarray, affine: np.ndarray
              ) -> tuple[np.ndarray, np.ndarray]:
    """Current heads and anchors `(b, 3)` m (a ground anchor stays where it was set)."""
    head = np.array([_point(centroid, affine, c0, int(bs.block[k]), bs.head0[k])
                     for k in range(len(bs))]).reshape(-1, 3)
    anchor = np.array([bs.anchor0[k] if bs.anchor_block[k] < 0 else
                       _point(centroid, affine, c0, int(bs.anchor_block[k]), bs.anchor0[k])
                       for k in range(len(bs))]).reshape(-1, 3)
    return head, anchor


def axial_forces(bs: BoltSet, head: np.ndarray, anchor: np.ndarray, plastic: np.ndarray,
                 status: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Axial forces `(b,)` N (tension positive, uncapped, 0 for broken bolts), axes `(b, 3)`
    from head to anchor, and elastic elongations `(b,)` m."""
    s = anchor - head
    length = np.linalg.norm(s, axis=1)
    axis = s / np.maximum(length, 1e-300)[:, None]
    x = length - bs.length0 - plastic
    n = np.where(status == BROKEN, 0.0, bs.pretension + bs.axial_stiffness * x)
    return n, axis, x


def stored_energy(bs: BoltSet, head: np.ndarray, anchor: np.ndarray, plastic: np.ndarray,
                  shear: np.ndarray, status: np.ndarray) -> float:
    """Energy (J) the intact bolts hold: `T0 x + ½ k_a x² + |S|² / (2 k_s)`."""
    _, _, x = axial_forces(bs, head, anchor, plastic, status)
    ks = bs.shear_stiffness
    e = bs.pretension * x + 0.5 * bs.axial_stiffness * x**2 + np.where(
        ks > 0, np.sum(shear**2, axis=1) / (2.0 * np.where(ks > 0, ks, 1.0)), 0.0)
    return float(np.sum(np.where(status == BROKEN, 0.0, e)))


@dataclass
class BoltStep:
    """The bolts in one step: force on the head block at its start `f (b, 3)` N, spring
    matrices `p (b, 3, 3)` N/m, T at the ends on the unknown columns `ti`, `tj (b, 3, 12)`
    (zeros for a ground anchor), and which bolts act (not broken)."""

    f: np.ndarray
    p: np.ndarray
    ti: np.ndarray
    tj: np.ndarray
    acting: np.ndarray
    axis: np.ndarray
    ka: np.ndarray
    ks: np.ndarray


def bolt_step(bs: BoltSet, c0: np.ndarray, centroid: np.ndarray, affine: np.ndarray,
              plastic: np.ndarray, shear: np.ndarray, status: np.ndarray) -> BoltStep:
    """Forces, spring matrices and T matrices of the bolts at the start of a step."""
    head, anchor = bolt_ends(bs, c0, centroid, affine)
    n, axis, _ = axial_forces(bs, head, anchor, plastic, status)
    acting = status != BROKEN
    at_cap = np.abs(n) >= bs.capacity * (1.0 - _AT_CAPACITY)
    s_at_cap = np.linalg.norm(shear, axis=1) >= bs.shear_capacity * (1.0 - _AT_CAPACITY)
    ka = np.where(acting & ~at_cap, bs.axial_stiffness, 0.0)
    ks = np.where(acting & ~s_at_cap, bs.shear_stiffness, 0.0)
    nn = np.einsum("bi,bj->bij", axis, axis)
    p = ka[:, None, None] * nn + ks[:, None, None] * (np.eye(3)[None] - nn)
    f = np.where(acting[:, None], n[:, None] * axis + shear, 0.0)
    ti = displacement_matrices(head, centroid[bs.block])
    ground = bs.anchor_block < 0
    tj = displacement_matrices(anchor, centroid[np.where(ground, 0, bs.anchor_block)])
    tj[ground] = 0.0
    return BoltStep(f=f, p=p, ti=ti, tj=tj, acting=acting, axis=axis, ka=ka, ks=ks)


def relative_step(step: BoltStep, bs: BoltSet, d: np.ndarray) -> np.ndarray:
    """Displacement of each anchor relative to its head in a step of block displacements
    `d (n, 12)` `(b, 3)` m (linear, as the step's equations see it)."""
    dj = np.where((bs.anchor_block < 0)[:, None], 0.0,
                  d[np.maximum(bs.anchor_block, 0)])
    return (np.einsum("bij,bj->bi", step.tj, dj)
            - np.einsum("bij,bj->bi", step.ti, d[bs.block]))


def update(bs: BoltSet, step: BoltStep, d: np.ndarray, c0: np.ndarray,
           centroid1: np.ndarray, affine1: np.ndarray, plastic: np.ndarray,
           shear: np.ndarray, status: np.ndarray, energy0: float
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The bolts after a step of block displacements `d (n, 12)` that ended at `centroid1`,
    `affine1`: plastic elongations, shear forces, states, and the energy (J) the step
    dissipated in them (work the blocks did on them minus what they store more)."""
    ds = relative_step(step, bs, d)
    work = float(np.sum((step.f + np.einsum("bij,bj->bi", step.p, ds)) * ds))
    head, anchor = bolt_ends(bs, c0, centroid1, affine1)
    n, axis, _ = axial_forces(bs, head, anchor, plastic, status)
    plastic1 = plastic + np.where(np.abs(n) > bs.capacity,
                                  (n - np.clip(n, -bs.capacity, bs.capacity))
                                  / np.where(bs.axial_stiffness > 0, bs.axial_stiffness, 1.0),
                                  0.0)
    yielded = (np.abs(n) > bs.capacity) | ((step.ka == 0) & (bs.axial_stiffness > 0))
    tangential = ds - np.einsum("bi,bi->b", ds, step.axis)[:, None] * step.axis
    s1 = shear + step.ks[:, None] * tangential
    s1 -= np.einsum("bi,bi->b", s1, axis)[:, None] * axis
    mag = np.linalg.norm(s1, axis=1)
    over = mag > bs.shear_capacity
    s1 = s1 * np.where(over, bs.shear_capacity / np.maximum(mag, 1e-300), 1.0)[:, None]
    yielded |= over
    moved = np.linalg.norm((anchor - head) - bs.span0, axis=1)
    yielded |= status == YIELDED  # a bolt that yielded stays yielded
    status1 = np.where(status == BROKEN, BROKEN,
                       np.where(moved > bs.rupture, BROKEN,
                                np.where(yielded, YIELDED, ELASTIC))).astype(np.int8)
    s1[status1 == BROKEN] = 0.0
    energy1 = stored_energy(bs, head, anchor, plastic1, s1, status1)
    return plastic1, s1, status1, work - (energy1 - energy0)


def recorded_forces(bs: BoltSet, c0: np.ndarray, centroid: np.ndarray, affine: np.ndarray,
                    plastic: np.ndarray, shear: np.ndarray, status: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Axial (tension positive) and shear force magnitudes `(b,)` N of the bolts now."""
    head, anchor = bolt_ends(bs, c0, centroid, affine)
    n, _, _ = axial_forces(bs, head, anchor, plastic, status)
    n = np.clip(n, -bs.capacity, bs.capacity)
    return n, np.where(status == BROKEN, 0.0, np.linalg.norm(shear, axis=1))
