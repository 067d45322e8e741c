"""Issue 12: a cut rock mass starts clean. A 6 m cube cut by three persistent sets at
1.5 m (examples/jointed_cube.json at half size): slivers merged, volume kept, neighbours
share their faces exactly, nothing overlaps, and the first step keeps a sensible Δt."""

from __future__ import annotations

from collections import defaultdict

import numpy as np
import pytest

from benchmarks.bench_jointed_cube import scene
from engine.contact.search import detect
from engine.step.simulation import Simulation
from schemas.convert import build_model, overlap_depth

SPACING = 1.5


@pytest.fixture(scope="module")
def cube() -> object:
    return build_model(scene(6.0))


def _free(built: object) -> list:
    return [b.polyhedron for b in built.model.blocks if not b.fixed]


def test_slivers_merge_and_volume_is_kept(cube: object) -> None:
    every = _free(build_model(scene(6.0, min_block_volume=0, min_block_width=0)))
    blocks = _free(cube)
    assert min(p.width for p in every) < 0.05 * SPACING  # the cut does make slivers
    assert min(p.width for p in blocks) >= 0.1 * SPACING - 1e-9
    assert any("thin block(s)" in w for w in cube.warnings)
    for got in (every, blocks):
        assert sum(p.volume for p in got) == pytest.approx(216.0, rel=1e-9)
    assert 50 < len(blocks) < len(every)


def test_neighbours_share_faces_and_never_overlap(cube: object) -> None:
    """Joint faces pair up plane by plane (equal area on both sides), no two blocks
    overlap (linear program on their convex pieces), and the contact detection at step 0
    within the first step's search finds nothing deeper than round-off."""
    blocks = _free(cube)
    area: dict[tuple, float] = defaultdict(float)
    for p in blocks:
        for n, off, a, tag in zip(p.face_normals, p.face_offsets, p.face_areas, p.face_tags,
                                  strict=True):
            if tag < 0:
                continue
            k = int(np.argmax(np.abs(n)))
            s = 1.0 if n[k] > 0 else -1.0
            area[(*np.round(s * n, 6), round(s * off, 6))] += s * a
    assert area and max(abs(v) for v in area.values()) < 1e-9 * 36.0
    lo = np.array([p.bounds[0] for p in blocks]) - 1e-9
    hi = np.array([p.bounds[1] for p in blocks]) + 1e-9
    from engine.contact.detection import aabb_pairs

    pairs = aabb_pairs(lo, hi)
    assert len(pairs) > len(blocks)
    assert max(overlap_depth(blocks[i], blocks[j]) for i, j in pairs.tolist()) < 1e-9
    sim = Simulation(cube.model)
    contacts = detect(sim.system, sim.state, 0.5 * sim.system.search_distance)
    assert len(contacts) and contacts.gap.min() > -1e-12


def test_first_steps_keep_a_sensible_time_step(cube: object) -> None:
    sim = Simulation(cube.model)
    assert sim.system.max_step_displacement >= 0.05 * SPACING - 1e-9
    for _ in range(3):
        sim.step()
    assert sim.state.last_dt >= 1e-5
    assert sim.state.diagnostics.max_penetration < 1e-3



def test_a_rock_mass_at_rest_runs_at_the_asked_time_step() -> None:
    """Issue 14: a cut rock mass that cannot slide (joints rougher than any of its planes
    is steep, φ 85°) settles onto springs that start unstretched and runs at the asked Δt
    throughout: every step is limited by the asked Δt alone, none is cut, and the blocks
    come to rest (the cuts on moving rock masses come from their motion)."""
    from benchmarks.pile import rock_mass_model
    from engine.model import JointMaterial

    model = rock_mass_model(2.5, dt=1e-3, duration=1.0)
    model.joint_materials = [JointMaterial(np.radians(85.0))]
    sim = Simulation(model)
    assert (~sim.system.fixed).sum() > 60
    for _ in range(80):
        sim.step()
    d = sim.state.diagnostics
    assert d.cuts == {} and d.limited_by == {"asked": 80}
    assert sim.state.time == pytest.approx(0.08)
    speed = np.linalg.norm(sim.state.velocity[~sim.system.fixed, :3], axis=1)
    assert np.median(speed) < 1e-4 and speed.max() < 1e-3  # from ~2e-3 m/s at 10 ms
