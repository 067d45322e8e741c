"""Global K assembly: the block-sparse and the small dense paths give the same matrix,
and every solver path gives the same displacements."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from engine import assembly as asm
from engine.solver import make_solver


def _random_system(rng: np.random.Generator, n: int = 6, c: int = 25, d: int = 6):
    """Blocks 0 and 3 fixed, random symmetric contact terms between random pairs."""
    row_of = np.full(n, -1)
    free = [b for b in range(n) if b not in (0, 3)]
    row_of[free] = np.arange(len(free))
    a = rng.normal(size=(n, d, d))
    diag = np.einsum("nij,nkj->nik", a, a) + 50.0 * np.eye(d)
    bi = rng.integers(0, n, c)
    bj = (bi + rng.integers(1, n, c)) % n
    t = rng.normal(size=(c, 3, 2 * d))
    ti, tj = t[:, :, :d], t[:, :, d:]
    nrm = rng.normal(size=(c, 3))
    nrm /= np.linalg.norm(nrm, axis=1)[:, None]
    kii, kij, kjj = asm.contact_stiffness(ti, tj, nrm, np.full(c, 3.0), np.full(c, 1.5))
    return row_of, diag, bi, bj, kii, kij, kjj


def test_dense_and_block_sparse_assembly_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(7)
    args = _random_system(rng)
    dense, ddiag = asm.block_system(*args)
    assert isinstance(dense, np.ndarray)
    monkeypatch.setattr(asm, "DENSE_MAX_UNKNOWNS", 0)
    bsr, sdiag = asm.block_system(*args)
    assert sp.issparse(bsr)
    np.testing.assert_allclose(bsr.toarray(), dense, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sdiag, ddiag, rtol=0, atol=1e-12)
    np.testing.assert_allclose(dense, dense.T, atol=1e-12)
    # a brute-force sum of every contact's 2×2 block stencil
    row_of, diag, bi, bj, kii, kij, kjj = args
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
    np.testing.assert_allclose(dense, ref, atol=1e-12)


def test_dense_direct_and_cg_solvers_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    rng = np.random.default_rng(11)
    args = _random_system(rng, n=60, c=400)
    monkeypatch.setattr(asm, "DENSE_MAX_UNKNOWNS", 0)
    k, kdiag = asm.block_system(*args)
    f = rng.normal(size=k.shape[0])
    x_cg = make_solver(k, 6, kdiag)(f, None)          # 348 unknowns: conjugate gradients
    x_dense = make_solver(k.toarray(), 6)(f, None)   # dense Cholesky
    np.testing.assert_allclose(x_cg, x_dense, rtol=1e-8, atol=1e-12)
    x_lu = make_solver(sp.csc_matrix(k)[:300, :300], 6)(f[:300], None)  # SuperLU
    np.testing.assert_allclose(k.toarray()[:300, :300] @ x_lu, f[:300], atol=1e-8)
