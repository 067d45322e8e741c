"""The step's stages on their own: a run saved and resumed from its State alone equals an
uninterrupted one bit for bit; the compiled motion, open-close and solver kernels against
plain numpy; the engine's shape rules (short functions, one module per stage)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla

from engine.contact.constraints import LOCKED, OPEN, SLIDING
from engine.contact.solvers._open_close_kernels import contact_loads, step_results, update_modes
from engine.dynamics import assembly as asm
from engine.dynamics._solver_kernels import cholesky, cholesky_solve, invert_spd_blocks, pcg_bsr
from engine.dynamics.state import load_state, save_state
from engine.geometry._transform_kernels import (
    T0,
    TA,
    block_vertices,
    move_blocks,
    point_motions,
    rotation_matrices,
)
from engine.step.simulation import Simulation, run
from tests.digest_cases import CASES

ENGINE = Path(__file__).resolve().parents[1] / "engine"
RNG = np.random.default_rng(7)


# --------------------------------------------------------------------------- checkpoints


@pytest.mark.parametrize("case", ["pile_100", "toppling", "cohesion"])
def test_resumed_run_equals_uninterrupted_run_bit_for_bit(tmp_path: Path, case: str) -> None:
    """Stop a run half-way, save its State, resume it in a fresh Simulation from the file
    alone: every later step and the final state are identical to the last bit."""
    full = Simulation(CASES[case]())
    half = Simulation(CASES[case]())
    n = 450 if case == "pile_100" else 20  # the pile lands at about step 400
    for _ in range(n):
        full.step()
        half.step()
    assert len(half.state.memory.key) > 0  # contacts carry memory into the resumed steps
    half.checkpoint(tmp_path / "state.npz")
    resumed = Simulation.resume(CASES[case](), tmp_path / "state.npz")
    for _ in range(40):
        a, b = full.step(), resumed.step()
        assert np.array_equal(a.d, b.d)
        assert np.array_equal(a.normal_force, b.normal_force)
    for name in ("centroid", "affine", "rotation", "velocity", "stress", "deepest"):
        assert np.array_equal(getattr(full.state, name), getattr(resumed.state, name)), name
    assert (full.state.time, full.state.dt, full.state.step) == (
        resumed.state.time, resumed.state.dt, resumed.state.step)
    assert full.state.energies == resumed.state.energies


def test_run_resumed_from_a_state_finishes_where_one_run_does(tmp_path: Path) -> None:
    """`run(model, resume_from=state)` continues to the model's duration."""
    model = CASES["incline"]()
    sim = Simulation(model)
    for _ in range(100):
        sim.step()
    save_state(sim.state, tmp_path / "s.npz")
    resumed = run(CASES["incline"](), resume_from=load_state(tmp_path / "s.npz"))
    whole = run(CASES["incline"]())
    assert resumed.steps == whole.steps
    assert np.array_equal(resumed.state.centroid, whole.state.centroid)


# --------------------------------------------------------------------------- motion kernels


def test_point_motion_is_t_times_v() -> None:
    """T(x) v of the compiled kernel equals the T matrices the assembly builds from it."""
    p, c = RNG.normal(size=(50, 3)), RNG.normal(size=(50, 3))
    v = RNG.normal(size=(50, 12))
    t = asm.displacement_matrices(p, c)
    np.testing.assert_allclose(point_motions(p, c, v), np.einsum("pij,pj->pi", t, v),
                               rtol=1e-13, atol=1e-13)
    # rotation about z moves (1, 0, 0) towards +y; a pure strain εx stretches x
    assert np.allclose(T0[:, :3], np.eye(3)) and TA[0, 1, 5] == 1.0 and TA[0, 0, 6] == 1.0


def test_rotation_matrices_are_exact_rotations() -> None:
    """Rodrigues: orthogonal, det 1, the axis unmoved, the angle its length (and the
    Taylor branch for tiny angles agrees with scipy)."""
    from scipy.spatial.transform import Rotation

    r = np.vstack([RNG.normal(size=(20, 3)), 1e-6 * RNG.normal(size=(5, 3))])
    m = rotation_matrices(r)
    np.testing.assert_allclose(m, Rotation.from_rotvec(r).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(m @ np.transpose(m, (0, 2, 1)), np.broadcast_to(np.eye(3), m.shape),
                               atol=1e-14)


def test_move_blocks_and_vertices() -> None:
    """A step of translation t, rotation r and strain ε maps X to c + t + R (I + ε) (X − c)."""
    d = np.zeros((1, 12))
    d[0, :3] = [1.0, -2.0, 0.5]
    d[0, 3:6] = [0.0, 0.0, np.pi / 2]
    d[0, 6] = 0.01
    c, a, rot = np.zeros((1, 3)), np.eye(3)[None].copy(), np.eye(3)[None].copy()
    move_blocks(d, c, a, rot)
    x = block_vertices(c, a, np.zeros(1, np.int64), np.array([[1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(x[0], [1.0, -2.0 + 1.01, 0.5], atol=1e-14)
    np.testing.assert_allclose(rot[0] @ [1, 0, 0], [0, 1, 0], atol=1e-15)


# --------------------------------------------------------------------------- open-close kernels


def _contact_case(c: int = 6, d: int = 6):
    n = 3
    bi, bj = RNG.integers(1, n, c), np.zeros(c, np.int64)
    dmap = np.arange(n * d).reshape(n, d)
    dmap[0] = -1  # block 0 fixed
    ti, tj = RNG.normal(size=(c, 3, d)), RNG.normal(size=(c, 3, d))
    normal = RNG.normal(size=(c, 3))
    normal /= np.linalg.norm(normal, axis=1)[:, None]
    tangent = np.cross(normal, [0.0, 0.0, 1.0])
    tangent /= np.linalg.norm(tangent, axis=1)[:, None]
    return n, d, bi, bj, dmap, ti, tj, normal, tangent


def test_contact_loads_are_the_penalty_forces_of_each_mode() -> None:
    """Closed: −kn d0 n (and the dashpot −cn max(d0, 0)/Δt n of a contact entering in the
    step); locked: minus the shear spring of shear0 + offset in the plane; sliding: minus the
    friction tan φ N* along t; applied as Tᵢᵀ F and −Tⱼᵀ F."""
    n, d, bi, bj, dmap, ti, tj, normal, tangent = _contact_case()
    mode = np.array([OPEN, LOCKED, SLIDING, LOCKED, SLIDING, OPEN], np.int8)
    d0 = -1e-4 * RNG.random(6)
    d0[3] = 2e-6  # a contact that enters within the step: its dashpot starts at the gap
    shear0, offset = 1e-5 * RNG.normal(size=(6, 3)), 1e-6 * RNG.normal(size=(6, 3))
    nstar, tan_phi, kn, ks = 1e5 * RNG.random(6), np.full(6, 0.5), 1e9, 5e8
    cn, dt = 1e6 * RNG.random(6), 1e-3
    f = np.zeros(n * d)
    fric_mag, fric = contact_loads(f, dmap, bi, bj, ti, tj, normal, d0, mode, shear0, offset,
                                   tangent, nstar, tan_phi, kn, ks, cn, dt)
    want = np.zeros(n * d)
    for k in range(6):
        if mode[k] == OPEN:
            continue
        force = (-kn * d0[k] - cn[k] * max(d0[k], 0.0) / dt) * normal[k]
        if mode[k] == LOCKED:
            r = shear0[k] + offset[k]
            force -= ks * (r - (r @ normal[k]) * normal[k])
        else:
            force -= tan_phi[k] * nstar[k] * tangent[k]
            assert fric_mag[k] == pytest.approx(tan_phi[k] * nstar[k])
        want[dmap[bi[k]]] += ti[k].T @ force
    np.testing.assert_allclose(f, want, rtol=1e-12, atol=1e-9)
    assert np.all(fric[mode != SLIDING] == 0)


#: contacts in no face-to-face patch (the kernels' `patch` argument)
NO_PATCH = np.full(4, -1, dtype=np.int64)


def test_update_modes_follows_table_2() -> None:
    """A closed contact pulled apart opens; a locked one whose shear beats friction slides;
    an open one that penetrates past the hysteresis closes; a sliding one whose slip
    reverses locks."""
    normal = np.tile([0.0, 0.0, 1.0], (4, 1))
    d0 = np.array([-1e-5, -1e-5, 1e-6, -1e-5])
    dr = np.array([[0, 0, 2e-5], [1e-3, 0, 0], [0, 0, -1e-5], [-1e-4, 0, 0]])
    mode = np.array([LOCKED, LOCKED, OPEN, SLIDING], np.int8)
    tangent = np.array([[1.0, 0, 0]] * 4)
    z3, z = np.zeros((4, 3)), np.zeros(4)
    out = update_modes(d0, normal, dr, z3, z3.copy(), mode, tangent, np.zeros(4, bool),
                       np.zeros(4, np.int64), np.zeros(4, np.int64), np.full(4, 0.5), z, z,
                       np.full(4, 5e3), z3, 1e9, 1e9, z.copy(), 1e-3, 1e-7, z.copy(), 2, 2,
                       NO_PATCH[:4], 0)
    new_mode, nstar, d1, fn, changed = out[0], out[2], out[3], out[6], out[7]
    assert list(new_mode) == [OPEN, SLIDING, LOCKED, LOCKED]
    np.testing.assert_allclose(d1, d0 + dr[:, 2])
    # a penetrating contact carries its spring: N* = −kn d1 (no force-free band)
    np.testing.assert_allclose(fn[[1, 3]], -1e9 * d1[[1, 3]])
    np.testing.assert_allclose(nstar[[1, 3]], -1e9 * d1[[1, 3]])
    assert changed


def test_exactly_touching_faces_do_not_flip_on_round_off() -> None:
    """Cut faces touch exactly (gap 0.0) and carry no force: a solve's round-off (1e-20 m)
    neither opens the closed one nor closes the open one when their resolution covers it,
    and does without one; beyond the resolution both flip as Table 2 says."""
    normal = np.tile([0.0, 0.0, 1.0], (2, 1))
    d0 = np.zeros(2)
    z3, z = np.zeros((2, 3)), np.zeros(2)

    def modes(dn: float, resolution: float) -> list[int]:
        dr = np.array([[0, 0, dn], [0, 0, -dn]])
        out = update_modes(d0, normal, dr, z3, z3.copy(), np.array([LOCKED, OPEN], np.int8),
                           np.zeros((2, 3)), np.ones(2, bool), np.zeros(2, np.int64),
                           np.zeros(2, np.int64), np.full(2, 0.5), z, z, z.copy(), z3, 1e9,
                           1e9, z.copy(), 1e-3, 0.0, np.full(2, resolution), 2, 2,
                           NO_PATCH[:2], 0)
        return list(out[0])

    assert modes(1e-20, 1e-11) == [LOCKED, OPEN]
    assert modes(1e-20, 0.0) == [OPEN, LOCKED]
    assert modes(1e-9, 1e-11) == [OPEN, LOCKED]


def test_a_contact_past_the_switch_cap_is_held_at_its_friction_limit() -> None:
    """A locked contact that has used its locked <-> sliding switches and is sheared past
    friction stays locked; its spring's anchor slides back so that ks × stretch is tan φ N
    (return mapping), and the kernel reports how far the anchor slid."""
    normal = np.array([[0.0, 0.0, 1.0]])
    d0, dr = np.array([-1e-5]), np.array([[1e-3, 0.0, 0.0]])
    z3, z = np.zeros((1, 3)), np.zeros(1)
    offset = z3.copy()
    out = update_modes(d0, normal, dr, z3, offset, np.array([LOCKED], np.int8),
                       np.array([[1.0, 0, 0]]), np.zeros(1, bool), np.zeros(1, np.int64),
                       np.full(1, 2, np.int64), np.full(1, 0.5), z, z, z.copy(), z3, 1e9,
                       1e9, z.copy(), 1e-3, 0.0, z.copy(), 2, 2, NO_PATCH[:1], 0)
    assert out[0][0] == LOCKED
    stretch = offset[0] + dr[0]  # N = 1e9 × 1e-5 = 1e4 N, friction 5e3 N
    assert 1e9 * stretch[0] == pytest.approx(5e3)
    assert out[10][0] == pytest.approx(1e-3 - 5e-6)


@pytest.mark.parametrize(("cohesion", "slides"), [(2000.0, False), (800.0, True)])
def test_a_bonded_patch_slips_as_a_whole(cohesion: float, slides: bool) -> None:
    """Four locked contacts of one patch (N = 1e4, 1e4, 2e3, 2e3 N; tan φ 0.5; each
    sheared by 4e3 N, 1.6e4 N in all) and cohesion c·A shared equally: the patch holds
    while 1.6e4 ≤ 0.5 × 2.4e4 + c·A, i.e. c·A ≥ 4e3 N. With c·A = 8e3 N every contact stays
    locked (the light ones carry more than their own 1e3 + 2e3 N); with 3.2e3 N the whole
    bond breaks and the contacts whose shear beats their friction alone slide."""
    normal = np.tile([0.0, 0.0, 1.0], (4, 1))
    d0 = np.array([-1e-5, -1e-5, -2e-6, -2e-6])
    dr = np.tile([4e-6, 0.0, 0.0], (4, 1))  # ks 1e9: 4e3 N of shear each
    z3, z = np.zeros((4, 3)), np.zeros(4)
    broken = np.zeros(4, bool)
    out = update_modes(d0, normal, dr, z3, z3.copy(), np.full(4, LOCKED, np.int8),
                       z3.copy(), broken, np.zeros(4, np.int64), np.zeros(4, np.int64),
                       np.full(4, 0.5), z, np.full(4, cohesion), z.copy(), z3, 1e9, 1e9,
                       z.copy(), 1e-3, 0.0, z.copy(), 2, 2, np.zeros(4, np.int64), 1)
    if slides:
        assert list(out[0]) == [LOCKED, LOCKED, SLIDING, SLIDING] and broken.all()
    else:
        assert list(out[0]) == [LOCKED] * 4 and not broken.any()


def test_reseat_loss_books_what_springs_lost_between_steps_not_gains() -> None:
    """The springs' energy at the end of a step that the next step's contacts do not start
    with is booked as dissipation; a spring starting with more is left to the watchdog."""
    from types import SimpleNamespace

    from engine.contact.solvers.open_close import reseat_loss

    system = SimpleNamespace(kn=1e9, ks=5e8)
    t = SimpleNamespace(d0=np.array([-1e-5, 2e-6]), shear0=np.array([[2e-6, 0.0, 0.0],
                                                                     [0.0, 0.0, 0.0]]))
    start = 0.5 * 1e9 * 1e-10 + 0.5 * 5e8 * 4e-12
    held = SimpleNamespace(contact_energy=start + 3.0)
    assert reseat_loss(system, held, t) == pytest.approx(3.0)
    assert reseat_loss(system, SimpleNamespace(contact_energy=start - 1.0), t) == 0.0


def test_a_parting_contact_loses_its_dashpot_not_its_spring() -> None:
    """A closed contact whose spring still presses while the blocks part keeps its spring
    (it stays closed) and drops the dashpot that would pull the blocks together."""
    normal = np.array([[0.0, 0.0, 1.0]])
    d0, dr = np.array([-2e-5]), np.array([[0.0, 0.0, 1e-5]])
    z3, z = np.zeros((1, 3)), np.zeros(1)
    cn = np.array([1e7])  # cn / Δt = 1e10 > kn: the dashpot alone would make it tensile
    out = update_modes(d0, normal, dr, z3, z3.copy(), np.array([LOCKED], np.int8),
                       np.array([[1.0, 0, 0]]), np.zeros(1, bool), np.zeros(1, np.int64),
                       np.zeros(1, np.int64), np.full(1, 0.5), z, z, z.copy(), z3, 1e9, 1e9,
                       cn, 1e-3, 0.0, z.copy(), 2, 2, NO_PATCH[:1], 0)
    assert out[0][0] == LOCKED
    assert cn[0] == 0.0
    assert out[6][0] == pytest.approx(1e9 * 1e-5)


def test_dashpots_after_the_step_go_to_rings_and_rebounds() -> None:
    """After the step a closed contact is damped normally where its relative velocity at
    the end points against the one at the start (a bounce, a ring) or the blocks part (a
    rebound), tangentially where its slip reversed (a shear ring); one still closing, or
    sliding one way all through the step (sliding, starting to topple), is not."""
    from types import SimpleNamespace

    from engine.contact.constraints import ContactSet
    from engine.contact.solvers.damping import ringing

    c = 4
    contacts = ContactSet(
        block_i=np.array([1, 2, 3, 4]), block_j=np.zeros(c, np.int64),
        kind=np.zeros(c, np.int8), point_i=np.zeros((c, 3)), point_j=np.zeros((c, 3)),
        normal=np.tile([0.0, 0.0, 1.0], (c, 1)), tangent=np.tile([1.0, 0.0, 0.0], (c, 1)),
        mode=np.full(c, LOCKED, np.int8), gap=np.zeros(c), key=np.zeros((c, 4), np.int64),
        face_tag=np.zeros(c, np.int64), joint_material=np.zeros(c, np.int64),
        cand_indptr=np.zeros(c + 1, np.int64), cand_normals=np.zeros((0, 3)))
    v0, v1 = np.zeros((5, 12)), np.zeros((5, 12))
    v0[1, :3], v1[1, :3] = [0.1, 0.0, -0.2], [0.05, 0.0, 0.1]    # bounces, slides on
    v0[2, :3], v1[2, :3] = [0.1, 0.0, -0.1], [-0.1, 0.0, -0.05]  # shear ring, still closing
    v0[3, :3], v1[3, :3] = [0.1, 0.02, 0.0], [0.2, 0.03, 0.0]    # slides one way
    v0[4, :3], v1[4, :3] = [0.0, 0.0, 0.01], [0.0, 0.0, 0.02]    # parts: a rebound
    before = SimpleNamespace(velocity=v0, centroid=np.zeros((5, 3)))
    ring_n, ring_t = ringing(before, contacts, v1)
    assert ring_n.tolist() == [True, False, False, True]
    assert ring_t.tolist() == [False, True, False, False]


def test_step_results_forces_and_dissipation() -> None:
    """A locked contact: normal force −kn d1 − cn e/Δt, shear force −ks × its stretch (no
    shear dashpot in the solve); the implicit springs dissipate ½ k Δ² of their change."""
    normal = np.array([[0.0, 0.0, 1.0]])
    d0, d1 = np.array([-1e-5]), np.array([-2e-5])
    dr = np.array([[3e-6, 0.0, -1e-5]])
    dr_t = np.array([[3e-6, 0.0, 0.0]])
    z3 = np.zeros((1, 3))
    cn, dt = np.array([2e5]), 1e-3
    nf, sf, stretch, fw, num, damp = step_results(
        d0, d1, normal, z3, z3, dr, dr_t, np.array([LOCKED], np.int8), z3, z3, np.zeros(1),
        1e9, 5e8, cn, dt)
    # spring + dashpot on the step's normal motion e = d1 − d0 (it was already closed)
    assert nf[0] == pytest.approx(2e4 + 2e5 * 1e-5 / dt)
    np.testing.assert_allclose(stretch[0], [3e-6, 0, 0])
    np.testing.assert_allclose(sf[0], [-5e8 * 3e-6, 0, 0])
    assert fw == 0.0
    assert num == pytest.approx(0.5 * 1e9 * 1e-10 + 0.5 * 5e8 * 9e-12)
    # the normal dashpot takes ½ (c/Δt)(e² + Δ²) (a = 0)
    assert damp == pytest.approx(2e5 / dt * 1e-10)


# --------------------------------------------------------------------------- solver kernels


def _spd(n: int) -> np.ndarray:
    a = RNG.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def test_dense_cholesky_solves_and_rejects_indefinite() -> None:
    k = _spd(30)
    f = RNG.normal(size=30)
    low, ok = cholesky(k)
    assert ok
    np.testing.assert_allclose(cholesky_solve(low, f), sla.solve(k, f), rtol=1e-10)
    assert not cholesky(k - 100.0 * np.eye(30))[1]


def test_block_inverses_and_pcg_on_a_block_sparse_system() -> None:
    """invert_spd_blocks inverts each block; pcg_bsr on a block tridiagonal SPD K with one
    uncoupled block row reaches the direct solution."""
    import scipy.sparse as sp

    m, b = 6, 6
    blocks = {(i, i): _spd(b) for i in range(m)}
    for i in range(m - 2):  # rows 0..4 coupled, row 5 alone
        c = 0.1 * RNG.normal(size=(b, b))
        blocks[(i, i + 1)], blocks[(i + 1, i)] = c, c.T
    dense = np.zeros((m * b, m * b))
    for (i, j), blk in blocks.items():
        dense[i * b:(i + 1) * b, j * b:(j + 1) * b] = blk
    k = sp.bsr_matrix(dense, blocksize=(b, b))
    k.sort_indices()
    diag = np.array([blocks[(i, i)] for i in range(m)])
    inv, ok = invert_spd_blocks(diag)
    assert ok
    np.testing.assert_allclose(inv @ diag, np.broadcast_to(np.eye(b), diag.shape), atol=1e-12)
    f = RNG.normal(size=m * b)
    x, its = pcg_bsr(k.indptr, k.indices, k.data, inv, np.arange(m - 1), f,
                     np.zeros(m * b), 1e-12, 500)
    assert its > 0
    np.testing.assert_allclose(x, np.linalg.solve(dense, f), rtol=1e-9, atol=1e-12)
