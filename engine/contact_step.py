"""Contacts of a step: how far each block may move (its displacement limit and search
reach), detection at the start of the step with joint materials, starting depths a spring
may plausibly have, and the contact patch areas that cohesion and tension act on."""

from __future__ import annotations

import time as _time

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from engine.contacts import OPEN, ContactSet, assign_joint_materials
from engine.detection import detect_contacts
from engine.motion import current_vertices, mass_properties, point_displacements
from engine.state import State
from engine.system import BlockSystem

#: a step's displacement limit: this × the displacement its start velocities predict ...
SEARCH_SAFETY = 2.0
#: ... and at least this fraction of the model's step limit (blocks at rest)
SEARCH_FLOOR = 0.02


def step_limit(system: BlockSystem, state: State, dt: float) -> np.ndarray:
    """Each block's displacement limit `(n,)` m for a step of `dt` s: SEARCH_SAFETY × what
    its velocity, gravity and loads predict, within [SEARCH_FLOOR, 1] × the model's step
    limit (0 for fixed blocks). A block that moves further is detected again with a larger
    limit, at the same Δt (:mod:`engine.stepping`)."""
    if not system.adaptive_search:
        return np.where(system.fixed, 0.0, system.max_step_displacement)
    accel = np.full(system.n, float(np.linalg.norm(system.gravity)))
    if system.loads:
        mass = system.density * mass_properties(system, state)[0]
        for b, _, f in system.loads:
            accel[b] += float(np.linalg.norm(f)) / mass[b]
    pred = point_displacements(system, state.velocity * dt) + accel * dt**2
    limit = np.clip(SEARCH_SAFETY * pred, SEARCH_FLOOR * system.max_step_displacement,
                    system.max_step_displacement)
    return np.where(system.fixed, 0.0, limit)


def step_search(system: BlockSystem, state: State, limit: np.ndarray) -> np.ndarray:
    """Each block's contact search reach `(n,)` m for a step whose points move at most
    `limit (n,)`: a block pair is searched within the sum of its two reaches. A block's
    reach is its limit, and at least the deepest penetration its contacts ended the last
    step with (detection keeps penetrations down to about -2 × the pair's search, so no
    contact is lost); half the model's full search distance on the first step, whose
    overlaps are the user's. A falling pile then looks for millimetres around each block,
    not for 1 % of the model's size, and a fast block does not widen the search of the
    others."""
    half = 0.5 * system.search_distance
    if not system.adaptive_search or state.deepest is None:
        return np.full(system.n, half)
    return np.minimum(np.maximum(limit, state.deepest), half)


def detect(system: BlockSystem, state: State, search: float | np.ndarray | None = None
           ) -> ContactSet:
    """Contacts within `search` m (default: the model's search distance; or each block's
    reach `(n,)`, see :func:`detect_contacts`) at the start of the step, with their joint
    materials."""
    contacts = detect_contacts(system.polys0, system.search_distance if search is None
                               else search, active=~system.fixed,
                               vertices=current_vertices(system, state))
    m = system.model
    assign_joint_materials(contacts, m.default_joint_material, m.joint_material_of_tag,
                           m.pair_joint_material)
    return contacts


def contact_areas(contacts: ContactSet) -> np.ndarray:
    """Each constraint's share `(c,)` m² of its contact patch.

    Constraints of one block pair with a common plane form a patch; its area is the area
    of the convex hull of their points in that plane, shared equally. Fewer than three
    points (edge or vertex contacts) carry no area.
    """
    out = np.zeros(len(contacts))
    if not len(contacts):
        return out
    key = np.column_stack([contacts.block_i, contacts.block_j,
                           np.round(contacts.normal * 1e6)]).astype(np.int64)
    _, group = np.unique(key, axis=0, return_inverse=True)
    group = group.ravel()
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        if len(idx) < 3:
            continue
        nrm = contacts.normal[idx[0]]
        u = np.cross(nrm, [1.0, 0, 0] if abs(nrm[0]) < 0.9 else [0, 1.0, 0])
        u /= np.linalg.norm(u)
        v = np.cross(nrm, u)
        p = contacts.point_j[idx]
        pts = np.column_stack([p @ u, p @ v])
        try:
            area = ConvexHull(pts).volume
        except QhullError:
            area = 0.0
        out[idx] = area / len(idx)
    return out


def _pair_depths(system: BlockSystem, state: State, contacts: ContactSet) -> np.ndarray:
    """How deep `(c,)` m each contact may plausibly start from its block pair's deepest
    penetration at the end of the last step (twice it), plus a slack of 1e-6 × the model
    size; deeper is a detection artefact."""
    mem = state.memory
    n = system.n
    plausible = np.full(len(contacts), 1e-6 * system.scale)
    if len(mem.key):
        pair_keys = mem.key[:, 0] * n + mem.key[:, 2]
        uniq, inv = np.unique(pair_keys, return_inverse=True)
        pair_prev = np.zeros(len(uniq))
        np.maximum.at(pair_prev, inv.ravel(), np.maximum(-mem.gap, 0.0))
        q = contacts.block_i * n + contacts.block_j
        pos = np.minimum(np.searchsorted(uniq, q), len(uniq) - 1)
        found = uniq[pos] == q
        plausible[found] += 2.0 * pair_prev[pos[found]]
    return plausible


def plausible_gaps(system: BlockSystem, state: State, contacts: ContactSet) -> int:
    """Start no spring with energy it never stored; returns how many contacts were found
    implausibly deep (detection artefacts, :func:`_pair_depths`).

    A contact found again starts no deeper than it ended (plus the exact rotation's
    second-order shift of its points), where re-detection picks a different plane
    (vertex-vertex, vertex-edge); one that ended open (pressed in within the open-close
    hysteresis) stored nothing and starts unstretched. A penalty spring started deeper
    would push the blocks apart with energy from nowhere; its initial gap (`contacts.gap`,
    in place) is limited to the plausible depth.
    """
    if state.step == 0 or not len(contacts) or not np.any(contacts.gap < 0):
        return 0
    mem = state.memory
    plausible = _pair_depths(system, state, contacts)
    allowed = plausible.copy()  # the depth a spring may start at
    row = mem.find(contacts.key)
    again = row >= 0
    if np.any(again) and state.last_d is not None:
        turn = np.linalg.norm(state.last_d[:, 3:6], axis=1) ** 2 * system.radius
        second = 0.5 * (turn[contacts.block_i] + turn[contacts.block_j])
        r = row[again]
        stored = np.where(mem.mode[r] != OPEN, np.maximum(-mem.gap[r], 0.0), 0.0)
        own = second[again] + stored
        plausible[again] = np.minimum(plausible[again], 1e-6 * system.scale + own)
        allowed[again] = np.minimum(allowed[again], system.touch_gap + own)
    artefacts = int(np.sum(contacts.gap < -plausible))
    deep = contacts.gap < -allowed
    contacts.gap[deep] = -allowed[deep]
    return artefacts


def find_contacts(system: BlockSystem, state: State, reach: np.ndarray
                  ) -> tuple[ContactSet, np.ndarray]:
    """The step's contacts within the blocks' `reach (n,)` m (:func:`step_search`), depths
    made plausible, and their patch areas `(c,)` m² (zero unless a joint has cohesion or
    tensile strength)."""
    clock = _time.perf_counter()
    contacts = detect(system, state, reach)
    state.diagnostics.relaxed_contacts += plausible_gaps(system, state, contacts)
    state.diagnostics.tick("detection", clock)
    areas = contact_areas(contacts) if system.needs_areas else np.zeros(len(contacts))
    return contacts, areas
