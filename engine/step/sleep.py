"""Sleeping blocks: model no more of a scene than moves (complementarity solve only).

An island of blocks (free blocks joined by contacts) sleeps when all their points have
moved slower than `sleep_velocity` for `sleep_time` (their velocities, and each step's
displacement over Δt: quasi-static steps zero the velocity) and every contact holds with a
margin (stuck, its shear force within SLEEP_MARGIN of its friction rim and below it by
twice the wake threshold): a block near its limit (a slope at FS 1.02 under a load that
creeps up) never sleeps, only one that rests. A sleeping block leaves the solve — it is
fixed for its awake neighbours, its velocity is zero, its contacts keep their forces (and
bonds) — and its pairs with other sleeping or fixed blocks are not searched (nor recorded
in a frame's contacts while they sleep). It wakes when the contacts its awake neighbours
press on it have changed its resultant force or moment, since it fell asleep, by more than
WAKE_RATIO of its weight (a block lands on it, a neighbour slides off it, a load creeps);
the step is then solved again with it awake, so the wake costs no motion. Blocks with
bolts, deformable blocks (their stresses relax slower than a rigid block comes to rest),
scenes with water (whose pressures follow the neighbours) and scenes under ground motion
never sleep.

A sleeping island rests on what held when it fell asleep: its joints' strengths, the body
acceleration (gravity and seismic coefficients), its blocks' point loads and fixed points,
and its neighbours. The state records that basis (:func:`record_basis`); a simulation that
starts from a state under another model (a strength-reduction or seismic trial, a stage)
wakes every island whose basis the new model changes (:func:`reconcile`): a weaker joint
wakes the islands with a contact on it, another body acceleration wakes every island, a
changed load wakes its block's island, and a stage that removes or fixes a block wakes the
islands of its neighbours (:func:`forget_basis`). A trial never starts asleep.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from engine.contact.constraints import LOCKED
from engine.contact.solution import StepResult
from engine.dynamics.motion import mass_matrices, mass_properties
from engine.dynamics.state import ContactMemory, State
from engine.dynamics.system import BlockSystem

#: a sleeping block's contacts must hold this far inside their capacity
SLEEP_MARGIN = 0.05
#: a sleeping block wakes when its resultant contact force (moment about its centroid, over
#: its radius) changes by more than this fraction of its weight
WAKE_RATIO = 1e-2


class Wake(Exception):
    """Sleeping blocks must wake: solve the step again with them awake."""


def enabled(system: BlockSystem) -> bool:
    """Whether blocks of this run may sleep."""
    c = system.controls
    return (c.contact_solver in ("complementarity", "newton") and c.sleep_velocity > 0
            and not system.elastic and system.water is None
            and system.model.ground_motion is None)


def _resultants(system: BlockSystem, state: State, block: np.ndarray, point: np.ndarray,
                force: np.ndarray) -> np.ndarray:
    """Each block's resultant `(n, 6)` of forces `force (k, 3)` N acting on `block (k,)` at
    `point (k, 3)`: force and moment about its centroid over its radius (N)."""
    out = np.zeros((system.n, 6))
    np.add.at(out[:, :3], block, force)
    arm = point - state.centroid[block]
    np.add.at(out[:, 3:], block, np.cross(arm, force) / system.radius[block, None])
    return out


def basis_loads(system: BlockSystem) -> np.ndarray:
    """What each block's sleep rests on `(n, 7)`: fixed (1) or not (0), then the resultant
    force (N) and moment about its initial centroid (N·m) of its point loads, with one unit
    of force per fixed point (a fixed point added or removed changes it)."""
    out = np.zeros((system.n, 7))
    out[:, 0] = system.fixed
    for b, p0, f in system.loads:
        out[b, 1:4] += f
        out[b, 4:7] += np.cross(p0 - system.c0[b], f)
    for b, p0 in system.fixed_points:
        out[b, 1:4] += 1.0
        out[b, 4:7] += p0 - system.c0[b]
    return out


def _joint_strengths(system: BlockSystem) -> np.ndarray:
    """The joint materials' strengths `(j, 3)`: tan φ, cohesion (Pa), tensile strength (Pa)."""
    return np.column_stack([system.tan_phi, system.cohesion, system.tension])


def record_basis(system: BlockSystem, state: State) -> None:
    """Record in `state` what its sleeping islands rest on under `system` (see the module's
    docstring)."""
    state.sleep_loads = basis_loads(system)
    state.sleep_joints = _joint_strengths(system)
    state.sleep_body = np.asarray(system.gravity, float).copy()


def forget_basis(arrays: dict[str, np.ndarray | None], blocks: np.ndarray) -> None:
    """Mark the per-block arrays' `blocks (n,) bool` as resting on nothing known (their
    islands wake in the next simulation): a stage changed their neighbours."""
    if arrays.get("sleep_loads") is not None:
        arrays["sleep_loads"][blocks] = np.nan


def touched_blocks(memory: ContactMemory, changed: np.ndarray) -> np.ndarray:
    """The blocks `(n,) bool` with a contact in `memory` to one of the blocks `changed
    (n,) bool`, and those blocks themselves."""
    out = changed.copy()
    i, j = memory.key[:, 0], memory.key[:, 2]
    out[i[changed[j]]] = True
    out[j[changed[i]]] = True
    return out


def _islands(system: BlockSystem, memory: ContactMemory) -> np.ndarray:
    """Each block's island `(n,)`: free blocks joined by the contacts of `memory` (a fixed
    block joins none)."""
    i, j = memory.key[:, 0], memory.key[:, 2]
    link = ~system.fixed[i] & ~system.fixed[j]
    graph = coo_matrix((np.ones(int(link.sum())), (i[link], j[link])),
                       shape=(system.n, system.n))
    return connected_components(graph, directed=False)[1]


def wake(system: BlockSystem, state: State, blocks: np.ndarray) -> None:
    """Wake the islands of the blocks `blocks (n,) bool` (in place); counted as wakes."""
    if state.asleep is None or not np.any(state.asleep & blocks):
        return
    if np.all(blocks):
        woken = state.asleep.copy()
    else:
        label = _islands(system, state.memory)
        woken = state.asleep & np.isin(label, label[blocks])
    state.asleep = state.asleep & ~woken
    state.quiet = np.where(woken, 0.0, state.quiet)
    if state.drift is not None:
        state.drift = np.where(woken[:, None], 0.0, state.drift)
    state.diagnostics.wakes += int(woken.sum())


def wake_all(system: BlockSystem, state: State) -> None:
    """Wake every sleeping block (in place): a trial starts with every block awake."""
    if state.asleep is not None:
        wake(system, state, np.ones(system.n, dtype=bool))


def reconcile(system: BlockSystem, state: State) -> None:
    """Wake the islands whose sleep the model of `system` no longer supports (see the
    module's docstring): a state carried to another model (a trial, a stage) keeps asleep
    only what rests on the same strengths, loads and neighbours; every island wakes when
    the body acceleration changed or the model cannot sleep at all."""
    if state.asleep is None or not np.any(state.asleep):
        return
    if len(state.asleep) != system.n:
        raise ValueError(f"the state has {len(state.asleep)} blocks, the model {system.n}")
    if (not enabled(system) or state.sleep_body is None
            or not np.array_equal(state.sleep_body, system.gravity)):
        wake_all(system, state)
        return
    blocks = np.zeros(system.n, dtype=bool)
    loads = state.sleep_loads
    if loads is None or loads.shape != (system.n, 7):
        blocks[:] = True
    else:
        blocks |= ~np.all(loads == basis_loads(system), axis=1)  # NaN: forgotten
    joints = _joint_strengths(system)
    old = state.sleep_joints
    if old is None or old.shape != joints.shape:
        blocks[:] = True
    else:
        weaker = np.flatnonzero(~np.all(old == joints, axis=1))
        mem = state.memory
        on = np.isin(mem.joint_material, weaker) | (mem.joint_material < 0)
        blocks[mem.key[on, 0]] = True
        blocks[mem.key[on, 2]] = True
    wake(system, state, blocks & ~system.fixed)
    if np.any(state.asleep):
        record_basis(system, state)


def check_wake(system: BlockSystem, state: State, res: StepResult) -> np.ndarray | None:
    """The sleeping blocks' change of resultant `(n, 6)` N since they fell asleep, with the
    step `res` (its contacts with awake blocks against the forces they had, by contact
    key); raises :class:`Wake`, the state's sleeping blocks updated, when a change exceeds
    WAKE_RATIO of a block's weight. None when nothing sleeps."""
    asleep = state.asleep
    if asleep is None or not np.any(asleep) or res.force is None:
        return None
    cs = res.contacts
    mem = state.memory
    row = mem.find(cs.key)
    before = np.where((row >= 0)[:, None], mem.force[np.maximum(row, 0)], 0.0)
    change = res.force - before  # on block i; block j gets the opposite
    on_i, on_j = asleep[cs.block_i], asleep[cs.block_j]
    drift = (np.zeros((system.n, 6)) if state.drift is None else state.drift.copy())
    drift += _resultants(system, state, cs.block_i[on_i], cs.point_i[on_i], change[on_i])
    drift += _resultants(system, state, cs.block_j[on_j], cs.point_j[on_j], -change[on_j])
    weight = _weights(system, state)
    woken = asleep & (np.linalg.norm(drift, axis=1) > WAKE_RATIO * weight)
    if np.any(woken):
        state.asleep = asleep & ~woken
        state.quiet = np.where(woken, 0.0, state.quiet)
        state.drift = np.where(woken[:, None], 0.0, state.drift if state.drift is not None
                               else 0.0)
        state.diagnostics.wakes += int(woken.sum())
        raise Wake
    return drift


def _speed(system: BlockSystem, v: np.ndarray) -> np.ndarray:
    """The fastest point's speed bound of each block `(n,)` m/s for velocities `v (n, d)`:
    translation, rotation times the radius, strain rate times the diameter."""
    return (np.linalg.norm(v[:, :3], axis=1) + system.radius * np.linalg.norm(v[:, 3:6], axis=1)
            + 2.0 * system.radius * np.abs(v[:, 6:]).max(axis=1, initial=0.0))


def _weights(system: BlockSystem, state: State) -> np.ndarray:
    """Each block's weight `(n,)` N (its mass times |g|; a floor for weightless scenes)."""
    g = max(float(np.linalg.norm(system.gravity)), 1.0)
    return system.density * mass_properties(system, state)[0] * g


def _holding(system: BlockSystem, state: State, res: StepResult) -> np.ndarray:
    """Blocks `(n,)` whose contacts all hold with a margin (none of :func:`weak_contacts`)."""
    cs = res.contacts
    weak = weak_contacts(system, state, res)
    out = np.ones(system.n, dtype=bool)
    out[cs.block_i[weak]] = False
    out[cs.block_j[weak]] = False
    return out


def weak_contacts(system: BlockSystem, state: State, res: StepResult) -> np.ndarray:
    """Contacts `(c,) bool` of the step that carry a force and do not hold with a margin:
    stuck, the shear force within SLEEP_MARGIN of the friction rim and, so that no change
    too small to wake a block can make one slip, below it by twice the wake threshold
    (WAKE_RATIO of the lighter block's weight); a bonded contact stuck holds (its capacity
    is its patch's)."""
    cs = res.contacts
    jm = cs.joint_material
    shear = np.linalg.norm(res.shear_force, axis=1)
    n = res.normal_force
    rim = system.tan_phi[jm] * np.maximum(n, 0.0)
    weight = np.where(system.fixed, np.inf, _weights(system, state))
    wake = WAKE_RATIO * np.minimum(weight[cs.block_i], weight[cs.block_j])
    rim = np.minimum((1.0 - SLEEP_MARGIN) * rim, rim - 2.0 * wake)
    bonded = ~res.broken if res.broken is not None else np.zeros(len(cs), dtype=bool)
    carrying = (n != 0.0) | (shear > 0.0)
    ok = (cs.mode == LOCKED) & (shear <= rim) & (n >= 0.0)
    ok |= bonded & (cs.mode == LOCKED)  # a bond holds it (its capacity is per patch)
    return carrying & ~ok


def _island_quiet(system: BlockSystem, res: StepResult, quiet: np.ndarray) -> np.ndarray:
    """Each block's island's shortest quiet time `(n,)` s: islands are the free blocks
    joined by the step's contacts (fixed blocks do not join them), so an island sleeps
    whole, as in Box2D, and no awake block rests on one that has just fallen asleep."""
    cs = res.contacts
    free = ~system.fixed
    link = free[cs.block_i] & free[cs.block_j]
    graph = coo_matrix((np.ones(int(link.sum())), (cs.block_i[link], cs.block_j[link])),
                       shape=(system.n, system.n))
    count, label = connected_components(graph, directed=False)
    shortest = np.full(count, np.inf)
    np.minimum.at(shortest, label, quiet)
    return shortest[label]


def update(system: BlockSystem, res: StepResult, after: State, dt: float,
           drift: np.ndarray | None) -> None:
    """After a step of `dt` s: each awake block's quiet time, the sleeping blocks'
    resultant change `drift` (:func:`check_wake`), and the blocks that fall asleep (their
    velocities zeroed; the kinetic energy that removes, below the threshold's, counts as
    numerical dissipation)."""
    if not enabled(system):
        return
    c = system.controls
    n = system.n
    asleep = np.zeros(n, dtype=bool) if after.asleep is None else after.asleep.copy()
    quiet = np.zeros(n) if after.quiet is None else after.quiet.copy()
    v = after.velocity
    speed = np.maximum(_speed(system, v), _speed(system, res.d / dt))  # quasi-static: d / Δt
    still = ~system.fixed & ~asleep & (speed < c.sleep_velocity) & _holding(system, after, res)
    if system.bolts is not None:  # bolted blocks stay awake (their links are constraints)
        bs = system.bolts
        still[bs.block] = False
        still[bs.anchor_block[bs.anchor_block >= 0]] = False
    quiet = np.where(still, quiet + dt, np.where(asleep, quiet, 0.0))
    falling = still & (_island_quiet(system, res, np.where(asleep, np.inf, quiet))
                       >= c.sleep_time)
    if np.any(falling):
        m = mass_matrices(system, after)
        kinetic = 0.5 * float(np.einsum("ni,nij,nj->", v[falling], m[falling], v[falling]))
        after.energies["numerical_dissipation"] += kinetic
        after.velocity = v.copy()
        after.velocity[falling] = 0.0
        asleep |= falling
    drift = np.zeros((n, 6)) if drift is None else drift
    drift[falling] = 0.0
    after.asleep, after.quiet, after.drift = asleep, quiet, drift
    if np.any(falling):
        record_basis(system, after)
