"""Global K assembly: the per-step plan gives the brute-force sum of every contact's
terms on both its dense and its block-sparse path, and every solver path agrees."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from engine.dynamics import assembly as asm
from engine.dynamics import solver
from engine.dynamics._assembly_kernels import fill_bsr, unit_contact_terms
from engine.dynamics.solver import (
    BlockJacobi,
    SolveError,
    block_jacobi,
    coupled_rows,
    make_solver,
    pcg,
    split_components,
)


def _random_contacts(rng: np.random.Generator, n: int = 6, c: int = 25, d: int = 6):
    """Blocks 0 and 3 fixed, random contacts between random pairs of blocks."""
    row_of = np.full(n, -1)
    free = [b for b in range(n) if b not in (0, 3)]
    row_of[free] = np.arange(len(free))
    a = rng.normal(size=(n, d, d))
    diag = np.einsum("nij,nkj->nik", a, a) + 50.0 * np.eye(d)
    bi = rng.integers(0, n, c)
    bj = (bi + rng.integers(1, n, c)) % n
    t = rng.normal(size=(c, 3, 2 * d))
    nrm = rng.normal(size=(c, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    return row_of, diag, bi, bj, t[:, :, :d].copy(), t[:, :, d:].copy(), nrm


def _brute_force(row_of, diag, bi, bj, ti, tj, nrm, kn, ks) -> np.ndarray:
    """K summed contact by contact from the paper's spring matrices (eqs. 24, 29)."""
    kii, kij, kjj = asm.contact_stiffness(ti, tj, nrm, kn, ks)
    m, d = int(row_of.max()) + 1, diag.shape[1]
    ref = np.zeros((m * d, m * d))
    for b in range(len(row_of)):
        if row_of[b] >= 0:
            r = slice(row_of[b] * d, row_of[b] * d + d)
            ref[r, r] += diag[b]
    for k in range(len(bi)):
        for x, y, blk in ((bi[k], bi[k], kii[k]), (bi[k], bj[k], kij[k]),
                          (bj[k], bi[k], kij[k].T), (bj[k], bj[k], kjj[k])):
            if row_of[x] >= 0 and row_of[y] >= 0:
                rx, ry = row_of[x] * d, row_of[y] * d
                ref[rx:rx + d, ry:ry + d] += blk
    return ref


def test_unit_contact_terms_combine_to_the_spring_matrices() -> None:
    rng = np.random.default_rng(3)
    *_, ti, tj, nrm = _random_contacts(rng)
    kn, ks = rng.uniform(0, 5, len(nrm)), rng.uniform(0, 5, len(nrm))
    unit = unit_contact_terms(ti, tj, nrm)
    direct = asm.contact_stiffness(ti, tj, nrm, kn, ks)
    for part in range(3):
        np.testing.assert_allclose(kn[:, None, None] * unit[:, part]
                                   + ks[:, None, None] * unit[:, 3 + part], direct[part],
                                   atol=1e-12)


@pytest.mark.parametrize("dense", [True, False])
def test_plan_matrix_is_the_sum_of_contact_terms(dense: bool,
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(7)
    args = _random_contacts(rng)
    if not dense:
        monkeypatch.setattr(asm, "DENSE_MAX_UNKNOWNS", 0)
    plan = asm.plan_system(*args)
    assert plan.dense is dense
    for _ in range(3):  # different open / closed / locked patterns on one plan
        c = len(args[2])
        kn = 3.0 * (rng.random(c) < 0.6)
        ks = 1.5 * (kn > 0) * (rng.random(c) < 0.5)
        k, kdiag = plan.matrix(kn, ks)
        full = k if dense else k.toarray()
        assert isinstance(k, np.ndarray) is dense
        ref = _brute_force(*args, kn, ks)
        np.testing.assert_allclose(full, ref, atol=1e-12)
        if not dense:  # the coupled rows and components from the modes are those of K
            _assert_components_of(plan.components, k)
        d = plan.d
        for r in range(plan.m):
            np.testing.assert_allclose(kdiag[r], ref[r * d:r * d + d, r * d:r * d + d],
                                       atol=1e-12)


def _assert_components_of(label: np.ndarray, k: sp.bsr_matrix) -> None:
    """`label` numbers the connected components of K's nonzero off-diagonal blocks."""
    np.testing.assert_array_equal(np.flatnonzero(label >= 0), coupled_rows(k))
    m = k.shape[0] // 6
    row = np.repeat(np.arange(m), np.diff(k.indptr))
    nonzero = np.any(k.data != 0.0, axis=(1, 2)) & (row != k.indices)
    graph = sp.csr_matrix((np.ones(nonzero.sum()), (row[nonzero], k.indices[nonzero])),
                          shape=(m, m))
    _, ref = connected_components(graph, directed=False)
    coupled = label >= 0
    # the same partition: one label per reference component and vice versa
    pairs = set(zip(label[coupled].tolist(), ref[coupled].tolist(), strict=True))
    assert len(pairs) == len({a for a, _ in pairs}) == len({b for _, b in pairs})
    assert sorted({a for a, _ in pairs}) == list(range(len(pairs)))


def test_dense_direct_and_cg_solvers_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(11)
    args = _random_contacts(rng, n=60, c=400)
    monkeypatch.setattr(asm, "DENSE_MAX_UNKNOWNS", 0)
    k, kdiag = asm.plan_system(*args).matrix(np.full(400, 3.0), np.full(400, 1.5))
    f = rng.normal(size=k.shape[0])
    x_cg = make_solver(k, 6, kdiag)(f, None)          # 348 unknowns: conjugate gradients
    x_dense = make_solver(k.toarray(), 6)(f, None)   # dense Cholesky
    np.testing.assert_allclose(x_cg, x_dense, rtol=1e-8, atol=1e-12)
    x_lu = make_solver(sp.csc_matrix(k)[:300, :300], 6)(f[:300], None)  # SuperLU
    np.testing.assert_allclose(k.toarray()[:300, :300] @ x_lu, f[:300], atol=1e-8)


def test_cg_solves_blocks_without_closed_contacts_on_their_own(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """With most contacts open, most block rows have no off-diagonal term: CG iterates on
    the coupled rows only and the isolated ones are exact from their block inverse."""
    rng = np.random.default_rng(5)
    args = _random_contacts(rng, n=80, c=300)
    monkeypatch.setattr(asm, "DENSE_MAX_UNKNOWNS", 0)
    kn = np.where(rng.random(300) < 0.1, 3.0, 0.0)  # ~30 closed contacts
    k, kdiag = asm.plan_system(*args).matrix(kn, 0.5 * kn)
    rows = coupled_rows(k)
    assert 0 < len(rows) < k.shape[0] // 6  # some coupled, some isolated
    f = rng.normal(size=k.shape[0])
    x_cg = make_solver(k, 6, kdiag)(f, rng.normal(size=k.shape[0]))  # any warm start
    np.testing.assert_allclose(k @ x_cg, f, atol=1e-9 * np.linalg.norm(f))
    x, _ = pcg(k, f, block_jacobi(kdiag), None, 1e-12, 1000, np.zeros(0, dtype=np.int64))
    isolated = np.setdiff1d(np.arange(k.shape[0] // 6), rows)
    idx = (6 * isolated[:, None] + np.arange(6)).ravel()
    np.testing.assert_allclose((k @ x)[idx], f[idx], atol=1e-9 * np.linalg.norm(f))


@pytest.mark.parametrize("closed", [0.1, 0.3])
def test_small_coupled_components_are_solved_exactly(
        monkeypatch: pytest.MonkeyPatch, closed: float) -> None:
    """Components of a few coupled blocks (a landing pile's) are factorized, CG iterates on
    the larger ones alone, and the answer is K's; at 30 % closed contacts one component
    is larger than the direct limit, so both paths run in one solve."""
    rng = np.random.default_rng(5)
    args = _random_contacts(rng, n=80, c=300)
    monkeypatch.setattr(asm, "DENSE_MAX_UNKNOWNS", 0)
    kn = np.where(rng.random(300) < closed, 3.0, 0.0)
    plan = asm.plan_system(*args)
    k, kdiag = plan.matrix(kn, 0.5 * kn)
    ptr, small, large = split_components(plan.components, solver.COMPONENT_DIRECT_MAX_BLOCKS)
    assert len(ptr) > 2 and (len(large) > 0) is (closed > 0.2)
    iterated = []
    pcg_of = solver.pcg
    monkeypatch.setattr(solver, "pcg", lambda *a: iterated.append(a[-1]) or pcg_of(*a))
    f = rng.normal(size=k.shape[0])
    x = make_solver(k, 6, kdiag, components=plan.components)(f, rng.normal(size=len(f)))
    np.testing.assert_allclose(k @ x, f, atol=1e-10 * np.linalg.norm(f))
    assert [len(r) for r in iterated] == [len(large)]
    monkeypatch.setattr(solver, "COMPONENT_DIRECT_MAX_BLOCKS", 0)  # everything by CG
    x_cg = make_solver(k, 6, kdiag, components=plan.components)(f, None)
    np.testing.assert_allclose(x, x_cg, rtol=1e-8, atol=1e-12 * np.abs(x).max())


def test_cg_refuses_a_matrix_that_is_not_positive_definite() -> None:
    k = sp.bsr_matrix(np.diag([1.0, 2, 3, 4, 5, -6] * 60), blocksize=(6, 6))
    with pytest.raises(SolveError, match="not positive definite"):
        make_solver(k, 6)


def test_block_jacobi_reinverts_only_changed_blocks() -> None:
    rng = np.random.default_rng(2)
    a = rng.normal(size=(40, 6, 6))
    diag = np.einsum("nij,nkj->nik", a, a) + 6.0 * np.eye(6)
    jac = BlockJacobi()
    np.testing.assert_allclose(jac(diag), np.linalg.inv(diag), rtol=1e-10, atol=1e-12)
    diag2 = diag.copy()
    diag2[[3, 17]] += 2.0 * np.eye(6)
    np.testing.assert_allclose(jac(diag2), np.linalg.inv(diag2), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(jac(diag[:10]), np.linalg.inv(diag[:10]), rtol=1e-10,
                               atol=1e-12)


def test_k_updated_from_the_last_equals_k_filled_afresh(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """A rock mass's open-close cycle changes a few of its contacts: K updated by their
    terms alone is K filled afresh (to round-off), cycle after cycle."""
    rng = np.random.default_rng(17)
    args = _random_contacts(rng, n=80, c=800)
    monkeypatch.setattr(asm, "DENSE_MAX_UNKNOWNS", 0)
    monkeypatch.setattr(asm, "UPDATE_MIN_CONTACTS", 100)
    fills = []
    monkeypatch.setattr(asm, "fill_bsr", lambda *a: fills.append(1) or fill_bsr(*a))
    plan, fresh = asm.plan_system(*args), asm.plan_system(*args)
    kn, ks = np.full(800, 3.0), np.full(800, 1.5)
    for _ in range(6):
        flip = rng.random(800) < 0.05
        kn = np.where(flip, 3.0 - kn, kn)
        ks = np.where(flip & (kn > 0), 1.5 - ks, ks)
        k, _ = plan.matrix(kn, ks)
        k = k.toarray()  # the plan's next matrix() updates its K in place
        fresh.last = None
        ref, _ = fresh.matrix(kn, ks)
        np.testing.assert_allclose(k, ref.toarray(), rtol=0, atol=1e-12)
    assert len(fills) == 1 + 6  # the plan filled its first K only; `fresh` every time



def test_threaded_loops_give_the_serial_bits(monkeypatch: pytest.MonkeyPatch) -> None:
    """The per-contact loops on numba's threads (contact matrices, K's fill, the open-close
    loads, relative displacements, the narrow phase in slices) sum every output in the
    serial order: a rock mass stepped with all of them on threads ends bit for bit where the
    serial run ends, whatever the number of threads."""
    from benchmarks.pile import rock_mass_model
    from engine.contact import detection
    from engine.dynamics import assembly
    from engine.step.simulation import Simulation

    def run(threads: bool) -> tuple[np.ndarray, ...]:
        monkeypatch.setattr(assembly, "threaded", lambda count: threads)
        monkeypatch.setattr(detection, "THREADED_MIN_PAIRS", 1 if threads else 10**9)
        monkeypatch.setattr(detection, "spare_core", lambda: threads)
        sim = Simulation(rock_mass_model(3.4, duration=1.0))
        for _ in range(6):
            sim.step()
        s = sim.state
        return s.centroid, s.velocity, s.rotation, s.memory.gap, s.memory.shear

    for a, b in zip(run(False), run(True), strict=True):
        assert np.array_equal(a.view(np.int64), b.view(np.int64))
