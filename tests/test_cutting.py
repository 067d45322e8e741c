"""Block cutting: the paper's wedge, joint sets, degenerate cuts, convex decomposition."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from engine.geometry.cutting.cut import CutResult, convex_decomposition, cut_blocks
from engine.geometry.joints import JointPlane, disc_polygon, joint_set_planes
from engine.geometry.polyhedron import (
    FACE_TAG_BOUNDARY,
    Polyhedron,
    dip_normal,
    face_centroids,
    face_normals_areas,
    mass_properties,
    winding_numbers,
)

# --------------------------------------------------------------------------- helpers


def box(lo: tuple[float, float, float], hi: tuple[float, float, float]) -> Polyhedron:
    """Axis-aligned box `[lo, hi]` with outward counter-clockwise faces."""
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1])
                  for x in (lo[0], hi[0])], dtype=float)
    f = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    return Polyhedron.from_faces(v, f)


def prism(outline: list[tuple[float, float]], z0: float, z1: float) -> Polyhedron:
    """Vertical prism over a counter-clockwise (seen from above) outline."""
    m = len(outline)
    v = [(x, y, z0) for x, y in outline] + [(x, y, z1) for x, y in outline]
    faces = [list(range(m))[::-1], list(range(m, 2 * m))]
    faces += [[i, (i + 1) % m, m + (i + 1) % m, m + i] for i in range(m)]
    return Polyhedron.from_faces(v, faces)


L_OUTLINE = [(0.0, 0.0), (4.0, 0.0), (4.0, 1.0), (1.0, 1.0), (1.0, 3.0), (0.0, 3.0)]


def plane(normal: np.ndarray | list[float], point: list[float], tag: int = 0,
          extent: np.ndarray | None = None) -> JointPlane:
    n = np.asarray(normal, float)
    return JointPlane(normal=n / np.linalg.norm(n), point=np.asarray(point, float), tag=tag,
                      extent=extent)


def piece_volume(block: Polyhedron, piece) -> float:
    return mass_properties(block.vertices, piece.face_indptr, piece.face_indices)[0]


def check_block(block: Polyhedron) -> None:
    """Valid surface; pieces (if any) convex, closed, tiling the volume, faces mapped right."""
    assert block.problems() == []
    if not block.pieces:
        assert block.is_convex
        return
    assert not block.is_convex
    total = 0.0
    s_cent = face_centroids(block.vertices, block.face_indptr, block.face_indices)
    for piece in block.pieces:
        sub = Polyhedron(block.vertices, piece.face_indptr, piece.face_indices,
                         np.zeros(len(piece.face_indptr) - 1, dtype=np.int64))
        assert sub.problems() == []
        assert sub.is_convex
        total += sub.volume
        normals, _ = face_normals_areas(block.vertices, piece.face_indptr, piece.face_indices)
        cents = face_centroids(block.vertices, piece.face_indptr, piece.face_indices)
        for k, f in enumerate(piece.face_surface.tolist()):
            if f < 0:
                continue
            assert normals[k] @ block.face_normals[f] > 1 - 1e-9
            assert abs((cents[k] - s_cent[f]) @ block.face_normals[f]) < 1e-6
    assert total == pytest.approx(block.volume, rel=1e-9)
    # every surface face is covered by piece faces of equal total area
    covered = np.zeros(block.n_faces)
    for piece in block.pieces:
        _, areas = face_normals_areas(block.vertices, piece.face_indptr, piece.face_indices)
        np.add.at(covered, piece.face_surface[piece.face_surface >= 0],
                  areas[piece.face_surface >= 0])
    np.testing.assert_allclose(covered, block.face_areas, rtol=1e-9, atol=1e-12)


def interior_points(block: Polyhedron) -> np.ndarray:
    """`(k, 3)` points strictly inside the block: vertex means of its convex pieces."""
    return np.array([block.vertices[p.vertex_ids].mean(axis=0)
                     for p in block.convex_pieces()])


def check_no_overlap(blocks: list[Polyhedron]) -> None:
    """Interior points of every block lie outside all other blocks."""
    pts = [interior_points(b) for b in blocks]
    for i, b in enumerate(blocks):
        w = winding_numbers(np.vstack(pts), b.vertices, b.face_indptr, b.face_indices)
        own = np.repeat(np.arange(len(blocks)), [len(p) for p in pts]) == i
        np.testing.assert_allclose(w[own], 1.0, atol=1e-6)
        np.testing.assert_allclose(w[~own], 0.0, atol=1e-6)


def check_cut(domain: Polyhedron, result: CutResult) -> None:
    """All blocks valid and the volume conserved to 1e-9 relative."""
    for b in result.blocks:
        check_block(b)
    total = sum(b.volume for b in result.blocks)
    assert total == pytest.approx(domain.volume, rel=1e-9)


# --------------------------------------------------------------------------- the wedge


WEDGE = np.array([(0, 3, 10), (-2.547792, -4, 10), (4.041452, -4, 10), (0.910297, -4, 6.127349)])


def scaled(tri: np.ndarray, factor: float) -> np.ndarray:
    c = tri.mean(axis=0)
    return c + factor * (tri - c)


def wedge_joints(factor: float = 1.25) -> list[JointPlane]:
    p = np.array([0.0, 3.0, 10.0])
    return [
        JointPlane(dip_normal(50, 110), p, 1, scaled(WEDGE[[0, 1, 3]], factor)),
        JointPlane(dip_normal(55, 240), p, 2, scaled(WEDGE[[0, 2, 3]], factor)),
    ]


def test_paper_wedge_gives_wedge_and_concave_base() -> None:
    domain = box((-10, -4, 0), (10, 10, 10))
    result = cut_blocks(domain, wedge_joints())
    check_cut(domain, result)
    assert len(result.blocks) == 2
    wedge, base = sorted(result.blocks, key=lambda b: b.volume)
    assert wedge.volume == pytest.approx(29.7708, rel=1e-4)
    assert len(wedge.vertices) == 4
    d = np.linalg.norm(wedge.vertices[:, None] - WEDGE[None], axis=2)
    assert d.min(axis=0).max() < 1e-5 and d.min(axis=1).max() < 1e-5
    assert sorted(wedge.face_tags.tolist()) == [-1, -1, 1, 2]
    assert wedge.is_convex and not base.is_convex
    assert base.volume == pytest.approx(domain.volume - wedge.volume, rel=1e-9)
    top = np.flatnonzero(base.face_normals[:, 2] > 1 - 1e-12)
    assert len(top) == 1  # one face, notched
    assert len(base.faces[top[0]]) == 7
    assert base.face_areas[top[0]] == pytest.approx(20 * 14 - 0.5 * 7 * 6.589244, rel=1e-6)
    assert sorted(set(base.face_tags.tolist())) == [FACE_TAG_BOUNDARY, 1, 2]
    check_no_overlap(result.blocks)
    assert result.warnings == []


def test_short_wedge_joints_leave_one_block() -> None:
    # joints shrunk to half the wedge faces: dangling cracks, nothing separates
    domain = box((-10, -4, 0), (10, 10, 10))
    result = cut_blocks(domain, wedge_joints(0.5))
    check_cut(domain, result)
    assert len(result.blocks) == 1
    assert result.blocks[0].is_convex
    assert result.blocks[0].n_faces == 6
    assert len(result.blocks[0].vertices) == 8
    assert any("cuts nothing" in w for w in result.warnings)


# --------------------------------------------------------------------------- joint sets


def test_cube_cut_by_three_sets_conserves_volume_without_overlap() -> None:
    domain = box((0, 0, 0), (10, 10, 10))
    joints = []
    for tag, (dip, ddir) in enumerate([(45, 135), (45, 315), (75, 45)]):
        joints += joint_set_planes(dip_normal(dip, ddir), [5.0, 5.0, 5.0], 3.0, domain, tag)
    result = cut_blocks(domain, joints)
    check_cut(domain, result)
    assert len(result.blocks) > 30
    check_no_overlap(result.blocks)
    tags = {int(t) for b in result.blocks for t in b.face_tags}
    assert tags == {FACE_TAG_BOUNDARY, 0, 1, 2}


def test_small_corner_blocks_merge_into_neighbours() -> None:
    """Three oblique sets leave corner slivers (~1e-5 m³ beside ~30 m³ blocks): by default
    blocks under 1/1000 of the median volume join a neighbour; volume is conserved."""
    domain = box((0, 0, 0), (10, 10, 10))
    joints = []
    for tag, (dip, ddir) in enumerate([(45, 135), (45, 315), (75, 45)]):
        joints += joint_set_planes(dip_normal(dip, ddir), [5.0, 5.0, 5.0], 3.4, domain, tag)
    every = cut_blocks(domain, joints, min_block_volume=0.0, min_block_width=0.0)
    merged = cut_blocks(domain, joints)
    check_cut(domain, every)
    check_cut(domain, merged)
    v_every = np.array([b.volume for b in every.blocks])
    v_merged = np.array([b.volume for b in merged.blocks])
    assert v_every.min() < 1e-4
    assert v_merged.min() >= 1e-3 * np.median(v_every)
    assert len(merged.blocks) < len(every.blocks)
    assert v_merged.sum() == pytest.approx(1000.0, rel=1e-9)
    assert any("merged into a neighbour" in w for w in merged.warnings)
    # an explicit threshold merges more
    coarse = cut_blocks(domain, joints, min_block_volume=1.0)
    check_cut(domain, coarse)
    assert min(b.volume for b in coarse.blocks) >= 1.0
    assert len(coarse.blocks) < len(merged.blocks)


def test_orthogonal_sets_give_identical_boxes() -> None:
    domain = box((0, 0, 0), (8, 6, 4))
    joints = joint_set_planes([1, 0, 0], [0, 0, 0], 2.0, domain, 0)
    joints += joint_set_planes([0, 1, 0], [0, 0, 0], 2.0, domain, 1)
    joints += joint_set_planes([0, 0, 1], [0, 0, 0], 2.0, domain, 2)
    assert len(joints) == 3 + 2 + 1
    result = cut_blocks(domain, joints)
    check_cut(domain, result)
    assert len(result.blocks) == 24
    for b in result.blocks:
        assert b.volume == pytest.approx(8.0, rel=1e-12)
        assert len(b.vertices) == 8 and b.n_faces == 6
        np.testing.assert_allclose(np.ptp(b.vertices, axis=0), [2, 2, 2], atol=1e-12)
    corners = sorted(tuple(np.round(b.bounds[0], 9)) for b in result.blocks)
    assert len(set(corners)) == 24


def test_joint_set_planes_members_and_extents() -> None:
    domain = box((0, 0, 0), (10, 10, 10))
    ext = disc_polygon([5, 5, 5], [0, 0, 1], 2.0, 8)
    members = joint_set_planes([0, 0, 2], [5, 5, 5], 2.5, domain, 7, ext)
    heights = sorted(float(m.point[2]) for m in members)
    assert heights == [2.5, 5.0, 7.5]  # 0 and 10 only touch the box
    for m in members:
        assert m.tag == 7
        np.testing.assert_allclose(m.normal, [0, 0, 1])
        np.testing.assert_allclose(m.extent[:, 2], m.point[2])
        np.testing.assert_allclose(m.extent[:, :2], ext[:, :2])


def test_disc_polygon_circumscribes_and_runs_counter_clockwise() -> None:
    n = dip_normal(60, 30)
    c = np.array([1.0, 2.0, 3.0])
    poly = disc_polygon(c, n, 2.0, 12)
    assert poly.shape == (12, 3)
    np.testing.assert_allclose((poly - c) @ n, 0, atol=1e-12)
    mids = 0.5 * (poly + np.roll(poly, -1, axis=0))
    np.testing.assert_allclose(np.linalg.norm(mids - c, axis=1), 2.0, rtol=1e-12)
    area_vec = 0.5 * np.cross(poly - c, np.roll(poly, -1, axis=0) - c).sum(axis=0)
    assert area_vec @ n > 0
    assert np.linalg.norm(area_vec) > np.pi * 4.0


# --------------------------------------------------------------------------- random cuts


@settings(max_examples=25, deadline=None)
@given(
    normals=st.lists(
        st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 3).filter(
            lambda v: np.linalg.norm(v) > 0.2), min_size=2, max_size=4),
    points=st.lists(st.tuples(*[st.floats(0.5, 3.5)] * 3), min_size=5, max_size=5),
    radius=st.floats(0.5, 3.0),
)
def test_random_cuts_conserve_volume_and_stay_valid(
    normals: list[tuple[float, float, float]],
    points: list[tuple[float, float, float]],
    radius: float,
) -> None:
    domain = box((0, 0, 0), (4, 3, 5))
    joints = [plane(n, list(p), tag=k) for k, (n, p) in enumerate(zip(normals, points,
                                                                       strict=False))]
    nb = np.asarray(normals[0], float) + [0.3, -0.2, 0.5]
    joints.append(plane(nb, list(points[-1]), tag=9,
                        extent=disc_polygon(points[-1], nb, radius, 10)))
    result = cut_blocks(domain, joints)
    check_cut(domain, result)
    assert not any("invalid" in w or "dropped" in w for w in result.warnings)


# --------------------------------------------------------------------------- degenerate cuts


def test_joint_through_domain_edges_and_vertices() -> None:
    domain = box((0, 0, 0), (2, 2, 2))
    # diagonal plane x = y through two vertical edges; plane through 3 corners
    result = cut_blocks(domain, [plane([1, -1, 0], [0, 0, 0], 0),
                                 plane([1, 1, 1], [2, 0, 0], 1)])
    check_cut(domain, result)
    assert len(result.blocks) == 4
    vols = sorted(b.volume for b in result.blocks)
    np.testing.assert_allclose(vols, [2 / 3, 2 / 3, 10 / 3, 10 / 3], rtol=1e-12)
    check_no_overlap(result.blocks)


def test_joint_on_domain_face_or_outside_cuts_nothing() -> None:
    domain = box((0, 0, 0), (2, 2, 2))
    joints = [plane([0, 0, 1], [0, 0, 2], 0), plane([1, 0, 0], [0, 0, 0], 1),
              plane([0, 0, 1], [0, 0, 2 + 1e-12], 2), plane([0, 1, 0], [0, 5, 0], 3)]
    result = cut_blocks(domain, joints)
    check_cut(domain, result)
    assert len(result.blocks) == 1
    assert result.blocks[0].n_faces == 6
    assert np.all(result.blocks[0].face_tags == FACE_TAG_BOUNDARY)
    assert sum("cuts nothing" in w for w in result.warnings) == 4, result.warnings


def test_joint_next_to_domain_face_leaves_no_sliver() -> None:
    domain = box((0, 0, 0), (2, 2, 2))
    result = cut_blocks(domain, [plane([0, 0, 1], [0, 0, 2 - 1e-10], 0)])
    check_cut(domain, result)
    assert len(result.blocks) == 1


def test_coincident_joints_cut_once() -> None:
    domain = box((0, 0, 0), (2, 2, 2))
    joints = [plane([0, 0, 1], [0, 0, 1], 4), plane([0, 0, -1], [1, 1, 1], 5),
              plane([1, 0, 0], [1, 0, 0], 6)]
    result = cut_blocks(domain, joints)
    check_cut(domain, result)
    assert len(result.blocks) == 4
    for b in result.blocks:
        assert b.n_faces == 6 and b.volume == pytest.approx(2.0, rel=1e-12)
        assert sorted(b.face_tags.tolist()) == [-1, -1, -1, -1, 4, 6]


def test_dangling_bounded_joint_does_not_separate() -> None:
    domain = box((0, 0, 0), (4, 4, 4))
    # a horizontal crack reaching in from x = 0 to x = 3 only
    ext = np.array([[-1, -1, 2], [3, -1, 2], [3, 5, 2], [-1, 5, 2]], dtype=float)
    result = cut_blocks(domain, [plane([0, 0, 1], [0, 0, 2], 3, ext)])
    check_cut(domain, result)
    assert len(result.blocks) == 1
    assert result.blocks[0].is_convex and result.blocks[0].n_faces == 6
    # the same crack reaching through separates
    ext[1:3, 0] = 5
    result = cut_blocks(domain, [plane([0, 0, 1], [0, 0, 2], 3, ext)])
    check_cut(domain, result)
    assert sorted(b.volume for b in result.blocks) == pytest.approx([32.0, 32.0])


def test_bounded_joints_cut_out_a_step() -> None:
    # a horizontal joint ending at a vertical one: an L-shaped remainder and a corner block
    domain = box((0, 0, 0), (4, 4, 4))
    horizontal = np.array([[-1, -1, 2], [2, -1, 2], [2, 5, 2], [-1, 5, 2]], dtype=float)
    vertical = np.array([[2, -1, 1.5], [2, 5, 1.5], [2, 5, 5], [2, -1, 5]], dtype=float)
    result = cut_blocks(domain, [plane([0, 0, 1], [0, 0, 2], 0, horizontal),
                                 plane([1, 0, 0], [2, 0, 0], 1, vertical)])
    check_cut(domain, result)
    vols = sorted(b.volume for b in result.blocks)
    assert vols == pytest.approx([16.0, 48.0])
    rest = max(result.blocks, key=lambda b: b.volume)
    assert not rest.is_convex and len(rest.pieces) >= 2
    check_no_overlap(result.blocks)


# --------------------------------------------------------------------------- concave shapes


def test_concave_domain_is_cut_into_concave_blocks() -> None:
    domain = prism(L_OUTLINE, 0.0, 2.0)
    assert domain.problems() == [] and not domain.is_convex
    result = cut_blocks(domain, [plane([0, 0, 1], [0, 0, 0.5], 0)])
    check_cut(domain, result)
    assert len(result.blocks) == 2
    for b in result.blocks:
        assert not b.is_convex
        assert b.n_faces == 8  # the L prism's faces, not the arrangement cells
    assert sorted(b.volume for b in result.blocks) == pytest.approx([3.0, 9.0])
    check_no_overlap(result.blocks)


def test_convex_decomposition_of_l_prism() -> None:
    block = prism(L_OUTLINE, 0.0, 2.0)
    dec = convex_decomposition(block)
    assert len(dec.pieces) >= 2
    np.testing.assert_array_equal(dec.face_indices, block.face_indices)
    np.testing.assert_allclose(dec.vertices[: len(block.vertices)], block.vertices)
    check_block(dec)
    assert sum(piece_volume(dec, p) for p in dec.pieces) == pytest.approx(12.0, rel=1e-12)


def test_convex_decomposition_keeps_convex_block_whole() -> None:
    block = box((0, 0, 0), (1, 2, 3))
    dec = convex_decomposition(block)
    assert dec.pieces == ()
    assert dec.volume == pytest.approx(6.0)


def test_concave_domain_without_joints_comes_back_whole() -> None:
    domain = prism(L_OUTLINE, 0.0, 2.0)
    result = cut_blocks(domain, [])
    assert result.warnings == []
    assert len(result.blocks) == 1
    block = result.blocks[0]
    check_block(block)
    assert block.n_faces == 8 and len(block.surface_vertex_ids) == 12
    assert block.volume == pytest.approx(12.0, rel=1e-12)
    assert 2 <= len(block.pieces) <= 3
