"""Contacts of a step: how far each block may move (its displacement limit and search
reach), detection at the start of the step with joint materials, starting depths a spring
may plausibly have, and the contact patches that cohesion and tension act on."""

from __future__ import annotations

import time as _time

import numpy as np

from engine.contact.constraints import OPEN, ContactSet, assign_joint_materials
from engine.contact.detection import detect_contacts
from engine.contact.patches import ContactPatches, contact_patches
from engine.contact.skin import detect_with_skin
from engine.dynamics.motion import current_vertices, mass_properties, point_displacements
from engine.dynamics.state import State
from engine.dynamics.system import BlockSystem

#: a step's displacement limit: this × the displacement its start velocities predict ...
SEARCH_SAFETY = 2.0
#: ... and at least this fraction of the model's step limit (blocks at rest)
SEARCH_FLOOR = 0.02


def step_limit(system: BlockSystem, state: State, dt: float) -> np.ndarray:
    """Each block's displacement limit `(n,)` m for a step of `dt` s: SEARCH_SAFETY × what
    its velocity, gravity and loads predict, within [SEARCH_FLOOR, 1] × the model's step
    limit (0 for fixed blocks). A block that moves further is detected again with a larger
    limit, at the same Δt (:mod:`engine.step.stepping`)."""
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


#: searches of a run reuse the last full detection's pairs and features while they cover
#: the step (:mod:`engine.contact.skin`; the same contacts, found in less time)
USE_SKIN = True


def detect(system: BlockSystem, state: State, search: float | np.ndarray | None = None,
           skin: bool | None = None) -> ContactSet:
    """Contacts within `search` m (default: the model's search distance; or each block's
    reach `(n,)`, see :func:`detect_contacts`) at the start of the step, with their joint
    materials; pairs of blocks that do not move (fixed or asleep) are left out. Searched
    with the skin in the state's workspace (`skin`, default USE_SKIN) when each block has
    a reach of its own, else in full."""
    active = state.awake(system.fixed)
    vertices = current_vertices(system, state)
    if (USE_SKIN if skin is None else skin) and np.ndim(search) == 1 and system.n > 1:
        contacts = detect_with_skin(system.polys0, search, active, vertices,
                                    system.vertex_block, system.thickness, state.workspace)
    else:
        contacts = detect_contacts(system.polys0, system.search_distance if search is None
                                   else search, active=active, vertices=vertices)
    m = system.model
    assign_joint_materials(contacts, m.default_joint_material, m.joint_material_of_tag,
                           m.pair_joint_material)
    return contacts


def _pairs(system: BlockSystem, key: np.ndarray, block_i: np.ndarray, block_j: np.ndarray
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block pairs of the memory's contacts `key (m, 4)` and of the step's contacts: the
    sorted distinct pairs of the memory, each memory row's pair and each contact's (-1
    where the memory has no contact of its pair)."""
    n = system.n
    mem_pair = key[:, 0] * n + key[:, 2]
    uniq, inv = np.unique(mem_pair, return_inverse=True)
    q = block_i * n + block_j
    pos = np.minimum(np.searchsorted(uniq, q), max(len(uniq) - 1, 0))
    found = (uniq[pos] == q) if len(uniq) else np.zeros(len(q), dtype=bool)
    return uniq, inv.ravel(), np.where(found, pos, -1)


def _pair_energy_cap(system: BlockSystem, state: State, contacts: ContactSet,
                     new: np.ndarray) -> None:
    """Make the contacts of each block pair shallower, in place, until the pair's normal
    springs start the step with no more energy than they ended the last one with: first
    the contacts found again (in proportion, if together they exceed it), then the new ones
    (`new (c,)`: keys not in the memory) within what is left. A pair the memory does not
    know starts unstretched."""
    mem = state.memory
    uniq, mem_pair, pair = _pairs(system, mem.key, contacts.block_i, contacts.block_j)
    closed = mem.mode != OPEN
    room = np.bincount(mem_pair[closed], weights=np.minimum(mem.gap[closed], 0.0) ** 2,
                       minlength=len(uniq))
    room = np.append(room, 0.0)
    slot = np.where(pair >= 0, pair, len(uniq))  # pairs without memory: one extra slot
    for part in (~new, new):
        start = np.bincount(slot[part], weights=np.minimum(contacts.gap[part], 0.0) ** 2,
                            minlength=len(uniq) + 1)
        over = start > room * (1 + 1e-12)
        scale = np.sqrt(np.where(over, room / np.maximum(start, 1e-300), 1.0))
        shrink = part & over[slot]
        contacts.gap[shrink] *= scale[slot[shrink]]
        room = np.maximum(room - np.minimum(start, room), 0.0)


def plausible_gaps(system: BlockSystem, state: State, contacts: ContactSet) -> int:
    """Start no spring with energy it never stored: the gaps `contacts.gap` are made
    shallower in place; returns how many contacts were found implausibly deep (more than
    1e-6 of the model's size beyond what they may start with: detection artefacts).

    - On the first step, overlaps of the blocks as given are geometry, not stored energy:
      those contacts start unstretched (the deepest is kept in the diagnostics).
    - A contact found again starts no deeper than it ended (plus the exact rotation's
      second-order shift of its points, where re-detection picks another plane at a vertex
      contact); one that ended open (pressed, but not pressing) starts unstretched.
    - A new contact (its key not in the memory: a feature changed, or a pair just met)
      starts no deeper than its block pair's deepest spring ended; and each pair's contacts
      are made shallower until its springs hold no more energy than they ended with.
    A penalty spring started deeper would push the blocks apart with energy from nowhere.
    """
    gap = contacts.gap
    if not len(contacts) or not np.any(gap < 0):
        return 0
    if state.step == 0:
        d = state.diagnostics
        d.initial_overlap = max(d.initial_overlap, float(-gap.min()))
        d.initial_overlaps = int(np.sum(gap < 0))
        gap[gap < 0] = 0.0
        return 0
    mem = state.memory
    row = mem.find(contacts.key)
    again = row >= 0
    allowed = np.zeros(len(contacts))
    if np.any(~again) and len(mem.key):
        uniq, mem_pair, pair = _pairs(system, mem.key, contacts.block_i, contacts.block_j)
        deepest = np.zeros(len(uniq))
        closed = mem.mode != OPEN
        np.maximum.at(deepest, mem_pair[closed], np.maximum(-mem.gap[closed], 0.0))
        met = ~again & (pair >= 0)
        allowed[met] = deepest[pair[met]]
    if np.any(again):
        r = row[again]
        stored = np.where(mem.mode[r] != OPEN, np.maximum(-mem.gap[r], 0.0), 0.0)
        if state.last_d is not None:
            turn = np.linalg.norm(state.last_d[:, 3:6], axis=1) ** 2 * system.radius
            stored += 0.5 * (turn[contacts.block_i[again]] + turn[contacts.block_j[again]])
        allowed[again] = stored
    artefacts = int(np.sum(gap < -(allowed + 1e-6 * system.scale)))
    np.maximum(gap, -allowed, out=gap)
    if len(mem.key):  # (with no memory, `allowed` is zero: every spring starts unstretched)
        _pair_energy_cap(system, state, contacts, ~again)
    return artefacts


def find_contacts(system: BlockSystem, state: State, reach: np.ndarray
                  ) -> tuple[ContactSet, ContactPatches]:
    """The step's contacts within the blocks' `reach (n,)` m (:func:`step_search`), depths
    made plausible, and their face-to-face patches (none unless a joint has cohesion or
    tensile strength: :mod:`engine.contact.patches`)."""
    clock = _time.perf_counter()
    contacts = detect(system, state, reach)
    state.diagnostics.relaxed_contacts += plausible_gaps(system, state, contacts)
    state.diagnostics.tick("detection", clock)
    patches = (contact_patches(contacts) if system.needs_areas
               else ContactPatches.none(len(contacts)))
    return contacts, patches
