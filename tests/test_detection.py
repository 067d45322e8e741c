"""Contact detection: broad phase, the four basic contact types, concave blocks, invariances."""

from __future__ import annotations

import hashlib

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from engine.contact.constraints import (
    EDGE_EDGE,
    LOCKED,
    OPEN,
    VERTEX_EDGE,
    VERTEX_FACE,
    VERTEX_VERTEX,
    ContactSet,
    assign_joint_materials,
)
from engine.contact.detection import aabb_pairs, decode_feature, detect_contacts, feature_code
from engine.geometry.boxes import box_pairs
from engine.geometry.cutting.cut import convex_decomposition
from engine.geometry.polyhedron import (
    ConvexPiece,
    Polyhedron,
    dip_normal,
    face_normals_areas,
    faces_to_csr,
)
from engine.geometry.shapes import prism

# --------------------------------------------------------------------------- shape helpers

BOX_FACES = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]


def box_vertices(lo, hi) -> np.ndarray:
    (x0, y0, z0), (x1, y1, z1) = lo, hi
    return np.array([(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0),
                     (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)], float)


def box(lo, hi, tags=None) -> Polyhedron:
    """Axis-aligned box; faces -z, +z, -y, +x, +y, -x."""
    return Polyhedron.from_faces(box_vertices(lo, hi), BOX_FACES, tags)


def hull_faces(points: np.ndarray, ids) -> list[list[int]]:
    """Faces (merged coplanar, counter-clockwise from outside) of the convex hull of
    `points[ids]`, as indices into `points`."""
    ids = np.asarray(ids)
    pts = points[ids]
    hull = ConvexHull(pts)
    scale = max(1.0, float(np.abs(pts).max()))
    planes: list[np.ndarray] = []
    for eq in hull.equations:
        if not any(np.abs(eq - q).max() < 1e-7 for q in planes):
            planes.append(eq)
    faces = []
    for eq in planes:
        n, d = eq[:3], eq[3]
        on = np.flatnonzero(np.abs(pts @ n + d) < 1e-9 * scale)
        c = pts[on].mean(axis=0)
        u = pts[on[0]] - c
        u /= np.linalg.norm(u)
        w = np.cross(n, u)
        ang = np.arctan2((pts[on] - c) @ w, (pts[on] - c) @ u)
        faces.append([int(ids[k]) for k in on[np.argsort(ang)]])
    return faces


def convex_block(points) -> Polyhedron:
    pts = np.asarray(points, float)
    used = np.unique(ConvexHull(pts).vertices)
    pts = pts[used]
    return Polyhedron.from_faces(pts, hull_faces(pts, np.arange(len(pts))))


def concave_block(vertices, faces, tags, piece_ids) -> Polyhedron:
    """A block with surface `faces` and convex pieces = hulls of the vertex id sets.

    Piece faces on a block face plane map to that face; the others are fictitious.
    """
    v = np.asarray(vertices, float)
    plain = Polyhedron.from_faces(v, faces, tags)
    pieces = []
    for ids in piece_ids:
        pf = hull_faces(v, ids)
        surf = []
        normals, _ = face_normals_areas(v, *faces_to_csr(pf))
        for f, n in zip(pf, normals, strict=True):
            hit = np.flatnonzero((plain.face_normals @ n > 1 - 1e-9)
                                 & (np.abs(plain.face_offsets - n @ v[f[0]]) < 1e-9))
            surf.append(int(hit[0]) if len(hit) else -1)
        indptr, indices = faces_to_csr(pf)
        pieces.append(ConvexPiece(indptr, indices, np.asarray(surf)))
    return Polyhedron.from_faces(v, faces, tags, tuple(pieces))


def oriented(v: np.ndarray, polys: list[list[int]]) -> list[list[int]]:
    """Polygons of a convex piece, each reversed if needed to face away from its centre."""
    centre = v[sorted({k for p in polys for k in p})].mean(axis=0)
    normals, _ = face_normals_areas(v, *faces_to_csr(polys))
    return [p if n @ (v[p].mean(axis=0) - centre) > 0 else p[::-1]
            for p, n in zip(polys, normals, strict=True)]


def l_block(tags=None) -> Polyhedron:
    """L-shaped block in x-z: floor [0,3]x[0,2]x[0,1] plus wall [0,1]x[0,2]x[1,3];
    the concave edge runs along y at x = 1, z = 1. Pieces: floor and wall."""
    v = np.array([(0, 0, 0), (3, 0, 0), (3, 0, 1), (1, 0, 1), (1, 0, 3), (0, 0, 3),
                  (0, 2, 0), (3, 2, 0), (3, 2, 1), (1, 2, 1), (1, 2, 3), (0, 2, 3),
                  (0, 0, 1), (0, 2, 1)], float)  # 12, 13: seam points
    faces = [[0, 1, 2, 3, 4, 5], [6, 11, 10, 9, 8, 7], [0, 6, 7, 1], [1, 7, 8, 2],
             [2, 8, 9, 3], [3, 9, 10, 4], [4, 10, 11, 5], [5, 11, 6, 0]]
    floor = [([0, 1, 2, 3, 12], 0), ([6, 13, 9, 8, 7], 1), ([0, 6, 7, 1], 2),
             ([1, 7, 8, 2], 3), ([2, 8, 9, 3], 4), ([3, 9, 13, 12], -1), ([0, 12, 13, 6], 7)]
    wall = [([12, 3, 4, 5], 0), ([13, 11, 10, 9], 1), ([3, 9, 10, 4], 5), ([4, 10, 11, 5], 6),
            ([5, 11, 13, 12], 7), ([12, 13, 9, 3], -1)]
    pieces = []
    for spec in (floor, wall):
        polys = oriented(v, [p for p, _ in spec])
        indptr, indices = faces_to_csr(polys)
        pieces.append(ConvexPiece(indptr, indices, np.array([t for _, t in spec])))
    return Polyhedron.from_faces(v, faces, tags, tuple(pieces))


def wedge_model() -> tuple[Polyhedron, Polyhedron]:
    """Paper example 6.1: concave base (block 0, two pieces) and the wedge (block 1)."""
    o, a = (0.0, 3.0, 10.0), (-2.547792, -4.0, 10.0)
    b, c = (4.041452, -4.0, 10.0), (0.910297, -4.0, 6.127349)
    v = [(-10, -4, 0), (10, -4, 0), (10, 10, 0), (-10, 10, 0), (-10, -4, 10), (10, -4, 10),
         (10, 10, 10), (-10, 10, 10), o, a, b, c,
         (0.910297, -4, 0), (-0.910297, 10, 0), (-0.910297, 10, 10)]  # seam points 12-14
    faces = [[0, 3, 2, 1], [0, 4, 7, 3], [1, 2, 6, 5], [3, 7, 6, 2],
             [4, 9, 8, 10, 5, 6, 7], [0, 1, 5, 10, 11, 9, 4], [9, 11, 8], [8, 11, 10]]
    tags = [-1, -1, -1, -1, -1, -1, 1, 2]
    left = [0, 12, 13, 3, 4, 9, 11, 8, 14, 7]
    right = [12, 1, 2, 13, 11, 10, 5, 6, 14, 8]
    base = concave_block(v, faces, tags, [left, right])
    wedge = Polyhedron.from_faces([o, a, b, c], [[0, 1, 2], [0, 3, 1], [0, 2, 3], [1, 3, 2]],
                                  [-1, 1, 2, -1])
    return base, wedge


def transformed(block: Polyhedron, rot: np.ndarray, shift: np.ndarray) -> Polyhedron:
    return block.moved(block.vertices @ rot.T + shift)


def as_rows(c: ContactSet) -> list[tuple]:
    """Order-independent description of a contact set (rounded)."""
    return sorted(
        (int(c.block_i[k]), int(c.block_j[k]), int(c.kind[k]),
         *np.round(c.point_i[k], 6), *np.round(c.point_j[k], 6),
         *np.round(c.normal[k], 6), round(float(c.gap[k]), 6))
        for k in range(len(c))
    )


def check_invariants(c: ContactSet) -> None:
    """Consistency every contact set must satisfy."""
    assert np.all(c.block_i > c.block_j)
    assert np.allclose(np.linalg.norm(c.normal, axis=1), 1.0)
    assert np.allclose(np.linalg.norm(c.tangent, axis=1), 1.0)
    assert np.allclose(np.einsum("ij,ij->i", c.normal, c.tangent), 0.0, atol=1e-12)
    assert np.allclose(c.gap, np.einsum("ij,ij->i", c.point_i - c.point_j, c.normal))
    assert np.array_equal(c.mode, np.where(c.gap < 0, LOCKED, OPEN))
    assert len(np.unique(c.key, axis=0)) == len(c)
    assert c.cand_indptr[-1] == len(c.cand_normals)
    pure = np.diff(c.cand_indptr) > 0
    assert np.all(np.isin(c.kind[pure], [VERTEX_EDGE, VERTEX_VERTEX]))


# --------------------------------------------------------------------------- feature codes


def test_feature_code_round_trip():
    code = feature_code([0, 3, 7], [0, 1, 2], [5, 0, 123456])
    piece, kind, index = decode_feature(code)
    assert piece.tolist() == [0, 3, 7]
    assert kind.tolist() == [0, 1, 2]
    assert index.tolist() == [5, 0, 123456]


# --------------------------------------------------------------------------- broad phase


@settings(max_examples=30, deadline=None, database=None)
@given(st.integers(0, 2**31 - 1), st.integers(2, 120))
def test_aabb_pairs_match_brute_force(seed, n):
    """The compiled sweep (each step) and the numpy one (a scene's overlap check) find
    exactly the brute-force pairs, in the same order."""
    rng = np.random.default_rng(seed)
    lo = rng.uniform(0, 10, (n, 3))
    hi = lo + rng.uniform(0, 1.5, (n, 3)) * rng.choice([0.2, 1.0, 6.0], (n, 1))
    ov = np.all(lo[:, None] <= hi[None], axis=2) & np.all(lo[None] <= hi[:, None], axis=2)
    a, b = np.nonzero(np.triu(ov, 1))
    want = sorted(map(list, zip(a.tolist(), b.tolist(), strict=True)))
    assert aabb_pairs(lo, hi).tolist() == want
    assert box_pairs(lo, hi).tolist() == want


@pytest.mark.parametrize("pairs", [aabb_pairs, box_pairs])
def test_aabb_pairs_touching_and_degenerate(pairs):
    lo = np.array([[0, 0, 0], [1, 0, 0], [2.5, 0, 0], [0, 0, 0]], float)
    hi = np.array([[1, 1, 1], [2, 1, 1], [3, 1, 1], [0, 0, 0]], float)
    assert pairs(lo, hi).tolist() == [[0, 1], [0, 3]]
    assert pairs(lo[:1], hi[:1]).shape == (0, 2)


def test_box_pairs_in_chunks_and_one_box_spanning_all(monkeypatch):
    """A base spanning every block (a candidate of all) and a sweep cut into chunks of a
    few candidates find the same pairs as one pass."""
    import engine.geometry.boxes as boxes

    rng = np.random.default_rng(7)
    lo = np.vstack([[-1, -1, -1], rng.uniform(0, 10, (200, 3))])
    hi = np.vstack([[11, 11, 11], lo[1:] + rng.uniform(0, 1.0, (200, 3))])
    whole = box_pairs(lo, hi)
    assert whole[:200].tolist() == [[0, k] for k in range(1, 201)]
    assert len(whole) > 200  # and pairs among the small boxes
    monkeypatch.setattr(boxes, "_CHUNK", 7)
    assert box_pairs(lo, hi).tolist() == whole.tolist() == aabb_pairs(lo, hi).tolist()


def test_far_apart_blocks_have_no_contacts():
    blocks = [box((0, 0, 0), (1, 1, 1)), box((1.2, 0, 0), (2, 1, 1))]
    assert len(detect_contacts(blocks, 0.19)) == 0
    assert len(detect_contacts(blocks, 0.21)) > 0


def test_fixed_pairs_are_skipped():
    blocks = [box((0, 0, -1), (3, 3, 0)), box((3, 0, -1), (6, 3, 0)), box((1, 1, 0), (2, 2, 1))]
    c = detect_contacts(blocks, 0.01, active=np.array([False, False, True]))
    assert set(zip(c.block_i.tolist(), c.block_j.tolist(), strict=True)) == {(2, 0)}
    c_all = detect_contacts(blocks, 0.01)
    assert (1, 0) in set(zip(c_all.block_i.tolist(), c_all.block_j.tolist(), strict=True))


# --------------------------------------------------------------------------- basic types


def test_cube_on_slab_face_to_face():
    slab = box((-2, -2, -1), (2, 2, 0), tags=[0, 7, 0, 0, 0, 0])
    cube = box((0, 0, 0), (1, 1, 1))
    c = detect_contacts([slab, cube], 0.01)
    check_invariants(c)
    assert len(c) == 4
    assert np.all(c.kind == VERTEX_FACE)
    assert np.all(c.block_i == 1) and np.all(c.block_j == 0)
    assert np.allclose(c.normal, [0, 0, 1])
    assert np.allclose(c.gap, 0.0)
    assert np.all(c.face_tag == 7)
    assert sorted(map(tuple, c.point_i[:, :2].tolist())) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert np.allclose(c.point_i, c.point_j)
    # swapped order: the same constraints, mirrored
    m = detect_contacts([cube, slab], 0.01)
    assert np.allclose(m.normal, [0, 0, -1]) and len(m) == 4
    assert np.all(m.face_tag == 7)


def test_penetration_and_gap_signs():
    slab = box((-2, -2, -1), (2, 2, 0))
    for dz, mode in ((-0.004, LOCKED), (0.004, OPEN)):
        c = detect_contacts([slab, box((0, 0, dz), (1, 1, 1 + dz))], 0.01)
        assert len(c) == 4
        assert np.allclose(c.gap, dz) and np.all(c.mode == mode)
    assert len(detect_contacts([slab, box((0, 0, 0.011), (1, 1, 1.011))], 0.01)) == 0


def test_cube_overhanging_slab_edge():
    """Cube half over the slab edge: two v-f on the slab, two e-e where the slab's top
    edge crosses the cube's bottom edges, nothing against the slab's side face."""
    slab = box((-2, -2, -1), (0, 2, 0))
    cube = box((-0.5, 0, -0.001), (0.5, 1, 0.999))
    c = detect_contacts([slab, cube], 0.01)
    check_invariants(c)
    assert np.allclose(c.normal, [0, 0, 1])
    assert np.allclose(c.gap, -0.001)
    kinds = sorted(c.kind.tolist())
    assert kinds == [VERTEX_FACE, VERTEX_FACE, EDGE_EDGE, EDGE_EDGE]
    ee = c.kind == EDGE_EDGE
    assert sorted(c.point_j[ee].round(9).tolist()) == [[0, 0, 0], [0, 1, 0]]
    assert np.allclose(c.point_i[ee][:, 2], -0.001)


def test_edge_contacts_on_a_joint_carry_its_tag():
    """The cube overhanging a slab whose top face lies on joint 7: the edge-edge
    constraints at the slab's edge lie on that face's plane and get its joint (and so its
    joint material)."""
    slab = box((-2, -2, -1), (0, 2, 0))
    tags = np.full(len(slab.faces), -1)
    tags[np.argmax(slab.face_normals[:, 2])] = 7
    slab = Polyhedron.from_faces(slab.vertices, [f.tolist() for f in slab.faces], tags)
    cube = box((-0.5, 0, -0.001), (0.5, 1, 0.999))
    c = detect_contacts([slab, cube], 0.01)
    assert sorted(c.kind.tolist()) == [VERTEX_FACE, VERTEX_FACE, EDGE_EDGE, EDGE_EDGE]
    assert c.face_tag.tolist() == [7, 7, 7, 7]
    assign_joint_materials(c, 0, {7: 1}, {})
    assert c.joint_material.tolist() == [1, 1, 1, 1]


def test_crossing_edges():
    """Two bars crossing at right angles, edge on edge: one e-e constraint."""
    low = box((-1, -0.5, -1), (1, 0.5, 0))
    rot = Rotation.from_rotvec([np.pi / 4, 0, 0]).as_matrix()  # edge down, along x
    bar = box((-1, -0.5, -0.5), (1, 0.5, 0.5))
    bar = transformed(bar, rot, np.zeros(3))
    bar = bar.moved(bar.vertices @ Rotation.from_rotvec([0, 0, np.pi / 2]).as_matrix().T)
    lift = np.sqrt(0.5) + 0.002
    upper = bar.moved(bar.vertices + [0.1, 0.2, lift])
    # the lower bar's top edges run along x at y = -0.5 and 0.5; the upper bar's bottom
    # edge runs along y at x = 0.1 and crosses both
    c = detect_contacts([low, upper], 0.01)
    check_invariants(c)
    assert np.all(c.kind == EDGE_EDGE) and len(c) == 2
    assert np.allclose(c.gap, 0.002)
    assert np.allclose(np.abs(c.normal @ [0, 0, 1]), 1.0)
    assert np.allclose(c.normal, [0, 0, 1])
    assert sorted(c.point_j.round(9).tolist()) == [[0.1, -0.5, 0.0], [0.1, 0.5, 0.0]]
    assert np.allclose(c.point_i - c.point_j, [0, 0, 0.002])


def test_tilted_crossing_edges_normal_is_cross_product():
    """Two wedge-shaped ridges whose edges cross skew: normal = e1 x e2 oriented j -> i."""
    roof = Polyhedron.from_faces(
        [(-1, -1, -1), (1, -1, -1), (1, 1, -1), (-1, 1, -1), (-1, 0, 0), (1, 0, 0)],
        [[0, 3, 2, 1], [0, 1, 5, 4], [2, 3, 4, 5], [1, 2, 5], [3, 0, 4]])
    rot = Rotation.from_rotvec([0, 0, 1.0]).as_matrix() @ np.diag([1, 1, -1.0])
    flip = roof.moved(roof.vertices @ rot.T)
    # mirrored by z -> -z: faces must be reversed to keep them outward
    flip = Polyhedron.from_faces(flip.vertices, [f[::-1].tolist() for f in roof.faces])
    tilt = Rotation.from_rotvec([0.05, 0.02, 0]).as_matrix()
    upper = transformed(flip, tilt, np.array([0.1, 0.05, 0.003]))
    c = detect_contacts([roof, upper], 0.02)
    check_invariants(c)
    assert len(c) == 1 and c.kind[0] == EDGE_EDGE
    e1 = np.array([1.0, 0, 0])
    e2 = tilt @ rot @ e1
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n) * np.sign(n[2])
    assert np.allclose(c.normal[0], n)
    assert c.point_j[0][1] == pytest.approx(0.0) and c.point_j[0][2] == pytest.approx(0.0)
    assert 0 < c.gap[0] < 0.004
    # on jointed ridges the plane still lies on no face (45 degrees off): no joint
    tagged = [Polyhedron.from_faces(b.vertices, [f.tolist() for f in b.faces],
                                    np.full(len(b.faces), 3)) for b in (roof, upper)]
    assert detect_contacts(tagged, 0.02).face_tag.tolist() == [-1]


def test_vertex_on_vertex_shortest_exit():
    """Corner on corner, diagonal: the plane with the largest gap wins (eq. 4)."""
    lower = box((-1, -1, -1), (0, 0, 0), tags=[0, 5, 0, 6, 0, 0])
    for shift, normal, tag in (((0.001, 0.002, 0.004), (0, 0, 1), 5),
                               ((0.004, 0.002, 0.001), (1, 0, 0), 6),
                               ((0.002, 0.003, 0.001), (0, 1, 0), 0)):
        upper = box(shift, np.add(shift, 1))
        c = detect_contacts([lower, upper], 0.01)
        check_invariants(c)
        assert len(c) == 1 and c.kind[0] == VERTEX_VERTEX
        assert np.allclose(c.normal[0], normal)
        assert c.face_tag[0] == tag
        assert np.allclose(c.point_i[0], shift) and np.allclose(c.point_j[0], 0)
        assert c.gap[0] == pytest.approx(np.dot(shift, normal))
        cands = c.cand_normals[c.cand_indptr[0]:c.cand_indptr[1]]
        assert len(cands) == 3  # the three face planes at the corner (crosses coincide)
        assert np.allclose(np.sort(np.abs(cands), axis=0), [[0, 0, 0], [0, 0, 0], [1, 1, 1]])


def test_overlapping_corners_exit_through_the_shallowest_face():
    """Corners overlapping by (1, 2, 0.5) mm: constraints at the corners of the overlap
    rectangle, all on the top face plane; no sideways edge-edge exits."""
    lower = box((-1, -1, -1), (0, 0, 0))
    shift = np.array([-0.001, -0.002, -0.0005])
    c = detect_contacts([lower, box(shift, shift + 1)], 0.01)
    check_invariants(c)
    assert np.allclose(c.normal, [0, 0, 1])
    assert np.allclose(c.gap, -0.0005)
    xy = sorted(map(tuple, np.round(c.point_j[:, :2], 9).tolist()))
    assert xy == [(-0.001, -0.002), (-0.001, 0.0), (0.0, -0.002), (0.0, 0.0)]


def test_vertex_on_edge():
    """A cube balanced on a corner just above a slab's edge: v-e, and the shortest exit
    (eq. 4) picks the face plane when open, a cross-product plane when penetrating."""
    slab = box((-2, -2, -1), (0, 2, 0), tags=[0, 3, 0, 4, 0, 0])
    rot = Rotation.from_euler("xy", [np.arctan(np.sqrt(0.5)), np.pi / 4]).as_matrix()
    cube = transformed(box((0, 0, 0), (1, 1, 1)), rot, np.zeros(3))
    low = int(np.argmin(cube.vertices[:, 2]))
    rel = cube.vertices - cube.vertices[low]
    assert np.allclose(rel[0], [-np.sqrt(0.5), 0, np.sqrt(0.5)])  # one edge across the slab
    for dz, normal, tag in ((0.001, [0, 0, 1], 3),
                            (-0.001, [np.sqrt(0.5), 0, np.sqrt(0.5)], -1)):
        cube_at = cube.moved(rel + [0, 0.3, dz])
        c = detect_contacts([slab, cube_at], 0.01)
        check_invariants(c)
        # penetrating, the edge across the slab also crosses the slab's edge (e-e) on the
        # same plane; open, it does not
        assert np.allclose(c.normal, normal) and np.allclose(c.gap, dz * normal[2])
        assert sorted(c.kind.tolist()) == ([EDGE_EDGE] if dz < 0 else []) + [VERTEX_EDGE]
        c = c.subset(c.kind == VERTEX_EDGE)
        assert np.allclose(c.point_i[0], [0, 0.3, dz]) and np.allclose(c.point_j[0], [0, 0.3, 0])
        assert np.allclose(c.normal[0], normal)
        assert c.gap[0] == pytest.approx(dz * normal[2])
        assert c.face_tag[0] == tag
        cands = c.cand_normals[c.cand_indptr[0]:c.cand_indptr[1]]
        assert len(cands) >= 2 and np.any(np.all(np.isclose(cands, normal), axis=1))


# --------------------------------------------------------------------------- concave blocks


def test_l_block_pieces_are_valid():
    blk = l_block()
    assert not blk.problems()
    assert len(blk.pieces) == 2
    assert all(np.sum(p.face_surface < 0) == 1 for p in blk.pieces)


def test_vertex_in_concave_corner_gets_one_plane_per_sub_angle():
    """A pyramid's apex pushed into the concave edge of an L block: two constraints
    (floor +z, wall +x), no deep false penetration."""
    lb = l_block(tags=list(range(8)))
    apex = np.array([1.0, 1.0, 1.0])
    axis = np.array([1.0, 0, 1.0]) / np.sqrt(2)
    u, w = np.array([-1.0, 0, 1.0]) / np.sqrt(2), np.array([0, 1.0, 0])
    base = [apex + 0.5 * axis + 0.2 * (np.cos(t) * u + np.sin(t) * w)
            for t in np.linspace(0, 2 * np.pi, 5)[:-1]]
    for pen in (0.0, 0.003):
        pyr = convex_block([apex - pen * axis, *(b - pen * axis for b in base)])
        c = detect_contacts([lb, pyr], 0.01)
        check_invariants(c)
        assert len(c) == 2
        assert sorted(map(tuple, c.normal.round(9).tolist())) == [(0, 0, 1), (1, 0, 0)]
        assert np.allclose(c.point_i, apex - pen * axis)
        assert np.allclose(c.gap, -pen / np.sqrt(2))
        assert sorted(c.face_tag.tolist()) == [4, 5]  # floor top (face 4), wall side (5)


def test_wedge_table_4():
    """Paper Table 4: six constraints at four positions on the two joint planes."""
    base, wedge = wedge_model()
    assert not base.problems() and not wedge.problems()
    c = detect_contacts([base, wedge], 0.01)
    check_invariants(c)
    n1 = dip_normal(50, 110)  # base's outward normal on J1 = from base (j) into wedge (i)
    n2 = dip_normal(55, 240)
    assert np.allclose(n1, [0.72, -0.26, 0.64], atol=0.01)
    assert np.allclose(-n2, [0.71, 0.41, -0.57], atol=0.01)
    assert np.all(c.block_i == 1) and np.all(c.block_j == 0)
    got = sorted((tuple(np.round(p, 2)), int(t)) for p, t in zip(c.point_i, c.face_tag,
                                                                 strict=True))
    want = sorted([((0.0, 3.0, 10.0), 1), ((0.0, 3.0, 10.0), 2), ((-2.55, -4.0, 10.0), 1),
                   ((0.91, -4.0, 6.13), 1), ((0.91, -4.0, 6.13), 2), ((4.04, -4.0, 10.0), 2)])
    assert got == want
    for k in range(len(c)):
        expect = n1 if c.face_tag[k] == 1 else n2
        assert np.allclose(c.normal[k], expect, atol=1e-5)
    assert np.allclose(c.gap, 0.0, atol=1e-5)
    assert np.allclose(c.point_i, c.point_j, atol=1e-5)


def test_wedge_sunk_stays_on_the_joint_planes():
    """Sunk 2 mm: every constraint stays on J1 or J2 with gap = -2 mm x n_z; the overlap
    polygons of the joint faces add edge-edge points but nothing else."""
    base, wedge = wedge_model()
    sunk = wedge.moved(wedge.vertices + [0, 0, -0.002])
    c = detect_contacts([base, sunk], 0.01)
    check_invariants(c)
    assert 6 <= len(c) <= 8
    n1, n2 = dip_normal(50, 110), dip_normal(55, 240)
    on1 = np.isclose(c.normal @ n1, 1.0)
    on2 = np.isclose(c.normal @ n2, 1.0)
    assert np.all(on1 | on2) and on1.sum() >= 3 and on2.sum() >= 3
    assert np.allclose(c.gap, -0.002 * c.normal[:, 2])
    # every constraint, edge-edge ones included, carries the joint of its plane
    assert np.array_equal(c.face_tag, np.where(on1, 1, 2))


# --------------------------------------------------------------------------- properties


def random_convex(rng: np.random.Generator, center, size: float) -> Polyhedron:
    pts = rng.normal(size=(12, 3))
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    return convex_block(np.asarray(center) + size * pts * rng.uniform(0.6, 1.0, (12, 1)))


def random_scene(seed: int) -> list[Polyhedron]:
    """Two random convex blocks or a convex block against an L block, close together."""
    rng = np.random.default_rng(seed)
    if seed % 3 == 0:
        lb = l_block()
        c = np.array([1.5, 1.0, 1.5]) + rng.uniform(-0.1, 0.1, 3)
        return [lb, random_convex(rng, c, 0.75)]
    a = random_convex(rng, [0, 0, 0], 1.0)
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    b = random_convex(rng, [0, 0, 0], 1.0)
    # slide b along d until it just stops overlapping a's hull-supporting slab
    shift = a.vertices @ d
    gap = rng.uniform(-0.01, 0.01)
    b = b.moved(b.vertices + d * (shift.max() - (b.vertices @ d).min() + gap))
    return [a, b]


U_BASE = [(0, 0), (3, 0), (3, 3), (2, 3), (2, 1), (1, 1), (1, 3), (0, 3)]  # open to +y


def property_scene(seed: int) -> list[Polyhedron]:
    """Scenes of the property tests: those of :func:`random_scene`, a random convex block
    in a U channel (two concave edges, three convex pieces) and two L blocks meeting corner
    into corner (concave against concave)."""
    rng = np.random.default_rng(seed)
    if seed % 4 == 1:
        # a block pushed into the channel's inner corner at (1, 1), within ±1 cm
        channel = convex_decomposition(prism(np.array(U_BASE, float), 2.0))
        b = random_convex(rng, [0.0, 0.0, 1.0], 0.45)
        lo = b.vertices[b.surface_vertex_ids].min(axis=0)
        return [channel, b.moved(b.vertices + [1 - lo[0], 1 - lo[1], 0]
                                 + rng.uniform(-0.01, 0.01, 3) * [1, 1, 0])]
    if seed % 4 == 3:
        # turned over, the second L's wall stands on the first's floor and its floor lies
        # on the first's wall: a frame of two concave blocks, ±1 cm
        lb = l_block()
        rot = Rotation.from_rotvec([0, np.pi, 0]).as_matrix()
        other = transformed(lb, rot, np.array([3.0, 0.0, 4.0]) + rng.uniform(-0.01, 0.01, 3))
        return [lb, other]
    return random_scene(seed)


@settings(max_examples=25, deadline=None, database=None)
@given(st.integers(0, 10**6))
def test_property_scenes_include_concave_pairs(seed):
    """The concave property scenes are valid blocks that do touch."""
    blocks = property_scene(4 * seed + 1 + 2 * (seed % 2))
    for b in blocks:
        assert b.problems() == []
    assert len(detect_contacts(blocks, 0.05)) > 0


@settings(max_examples=25, deadline=None, database=None)
@given(st.integers(0, 10**6))
def test_swapping_blocks_mirrors_constraints(seed):
    a, b = property_scene(seed)
    c1 = detect_contacts([a, b], 0.02)
    c2 = detect_contacts([b, a], 0.02)
    check_invariants(c1)
    check_invariants(c2)
    mirror = ContactSet(block_i=1 - c2.block_j, block_j=1 - c2.block_i, kind=c2.kind,
                        point_i=c2.point_j, point_j=c2.point_i, normal=-c2.normal,
                        gap=c2.gap)
    assert as_rows(c1) == as_rows(mirror)


@settings(max_examples=25, deadline=None, database=None)
@given(st.integers(0, 10**6), st.integers(0, 10**6))
def test_rigid_motion_of_scene_moves_constraints(seed, seed2):
    """Moving the whole scene moves points and turns normals and candidate planes with
    it; keys, kinds and gaps stay; tangents stay unit vectors in the contact plane."""
    blocks = property_scene(seed)
    rng = np.random.default_rng(seed2)
    rot = Rotation.random(random_state=rng).as_matrix()
    shift = rng.uniform(-5, 5, 3)
    c1 = detect_contacts(blocks, 0.02)
    c2 = detect_contacts([transformed(b, rot, shift) for b in blocks], 0.02)
    check_invariants(c2)
    assert len(c1) == len(c2)
    o1 = np.lexsort(c1.key.T[::-1])
    o2 = np.lexsort(c2.key.T[::-1])
    assert np.array_equal(c1.key[o1], c2.key[o2])
    assert np.array_equal(c1.kind[o1], c2.kind[o2])
    assert np.allclose(c1.gap[o1], c2.gap[o2], atol=1e-9)
    assert np.allclose(c1.normal[o1] @ rot.T, c2.normal[o2], atol=1e-7)
    assert np.allclose(c1.point_i[o1] @ rot.T + shift, c2.point_i[o2], atol=1e-7)
    assert np.allclose(c1.point_j[o1] @ rot.T + shift, c2.point_j[o2], atol=1e-7)
    assert np.allclose(np.linalg.norm(c2.tangent, axis=1), 1.0)
    assert np.allclose(np.einsum("ij,ij->i", c2.tangent, c2.normal), 0.0, atol=1e-12)
    for a, b in zip(o1, o2, strict=True):
        n1 = c1.cand_normals[c1.cand_indptr[a]:c1.cand_indptr[a + 1]]
        n2 = c2.cand_normals[c2.cand_indptr[b]:c2.cand_indptr[b + 1]]
        assert np.allclose(n1 @ rot.T, n2, atol=1e-7)


@settings(max_examples=25, deadline=None, database=None)
@given(st.integers(0, 10**6), st.floats(0.011, 0.5))
def test_separated_blocks_produce_nothing(seed, sep):
    a, b = property_scene(seed)
    d = np.array([0.0, 0.0, 1.0])
    top = a.vertices[a.surface_vertex_ids] @ d
    low = b.vertices[b.surface_vertex_ids] @ d
    b = b.moved(b.vertices + d * (top.max() - low.min() + sep))
    assert len(detect_contacts([a, b], 0.01)) == 0


@settings(max_examples=25, deadline=None, database=None)
@given(st.integers(0, 10**6))
def test_contacts_are_near_both_blocks(seed):
    """Every contact point lies on (within snap of) its block's surface region."""
    blocks = property_scene(seed)
    c = detect_contacts(blocks, 0.02)
    for k in range(len(c)):
        for blk, p in ((blocks[c.block_i[k]], c.point_i[k]), (blocks[c.block_j[k]], c.point_j[k])):
            lo, hi = blk.bounds
            assert np.all(p >= lo - 1e-9) and np.all(p <= hi + 1e-9)
        assert c.gap[k] > -0.04 and c.gap[k] < 0.02 + 1e-6


def test_keys_are_stable_under_small_motion():
    lb = l_block()
    cube = box((1.2, 0.5, 1.0), (1.7, 1.0, 1.5))
    c1 = detect_contacts([lb, cube], 0.01)
    rot = Rotation.from_rotvec([0.001, -0.002, 0.003]).as_matrix()
    moved = transformed(cube, rot, np.array([0.0003, -0.0002, -0.0004]))
    c2 = detect_contacts([lb, moved], 0.01)
    assert len(c1) == 4
    assert c1.key.tolist() == c2.key.tolist()
    assert len({tuple(k) for k in c1.key.tolist()}) == 4


def test_grid_of_boxes_contacts():
    """A 3 x 3 x 2 stack of unit boxes: every face neighbour pair is in contact with a
    plane along their shared face; diagonal neighbours may touch at corners only."""
    blocks = [box((x, y, z), (x + 1, y + 1, z + 1)) for x in range(3) for y in range(3)
              for z in range(2)]
    c = detect_contacts(blocks, 0.01)
    check_invariants(c)
    centers = np.array([b.centroid for b in blocks])
    d = centers[c.block_i] - centers[c.block_j]
    face_nb = np.abs(d).sum(axis=1) == 1
    assert np.allclose(c.normal[face_nb], d[face_nb])
    pairs = {(int(i), int(j)) for i, j, f in zip(c.block_i, c.block_j, face_nb, strict=True)
             if f}
    assert len(pairs) == 3 * 3 * 1 + 2 * (2 * 3 * 2)
    assert np.allclose(c.gap, 0.0)


# --------------------------------------------------------------------------- regression


def jittered_boxes(n_side: tuple[int, int, int], seed: int = 0) -> list[Polyhedron]:
    """Boxes on a 1 m grid, shrunk, shifted and rotated by up to ~1 mm / 1 mrad."""
    rng = np.random.default_rng(seed)
    unit = box_vertices((-0.5, -0.5, -0.5), (0.5, 0.5, 0.5))
    out = []
    for ix in range(n_side[0]):
        for iy in range(n_side[1]):
            for iz in range(n_side[2]):
                rot = Rotation.from_rotvec(rng.uniform(-1e-3, 1e-3, 3)).as_matrix()
                v = (unit * (1.0 - rng.uniform(0, 5e-4, 3))) @ rot.T + [ix, iy, iz]
                out.append(Polyhedron.from_faces(v + rng.uniform(-5e-4, 5e-4, 3), BOX_FACES))
    return out


def regression_scenes() -> list[tuple[str, list[Polyhedron], float]]:
    """Scenes whose contact sets were recorded from the first (numpy) implementation."""
    scenes = [(f"random{seed}", random_scene(seed), 0.05) for seed in range(9)]
    base, wedge = wedge_model()
    sunk = wedge.moved(wedge.vertices + [0.0, 0.0, -0.01])
    scenes.append(("l-block, base, sunk wedge", [l_block(), base, sunk], 0.05))
    scenes.append(("jittered boxes", jittered_boxes((4, 3, 2)), 0.005))
    rng = np.random.default_rng(5)
    hulls = [random_convex(rng, [0.55 * i, 0.55 * j, 0.55 * k], 0.5)
             for i in range(3) for j in range(2) for k in range(2)]
    scenes.append(("random hulls", hulls, 0.02))
    return scenes


def digest(c: ContactSet) -> tuple:
    """Count, kinds, hash of the sorted keys, and sums of gaps, normals and candidates."""
    order = np.lexsort(c.key.T[::-1])
    key = np.ascontiguousarray(c.key[order])
    return (len(c), np.bincount(c.kind, minlength=4).tolist(),
            hashlib.sha1(key.tobytes()).hexdigest()[:16],
            round(float(np.abs(c.gap).sum()), 9),
            round(float((c.normal[order] @ [1.0, 2.0, 3.0]) @ np.arange(1, len(c) + 1)), 6),
            int(c.cand_indptr[-1]))


#: digests of :func:`regression_scenes` recorded from the first (numpy) implementation
#: (one updated for the vertex-face shortest-exit rule, see below)
RECORDED = dict([
    ('random0', (2, [2, 0, 0, 0], 'ebb82c29c875fff5', 0.054968315, 3.0, 0)),
    ('random1', (0, [0, 0, 0, 0], 'da39a3ee5e6b4b0d', 0.0, 0.0, 0)),
    ('random2', (2, [0, 1, 1, 0], 'ccce8ec9a01a250f', 0.045068201, 4.3892, 2)),
    ('random3', (1, [1, 0, 0, 0], 'fd698f614464a082', 0.013440465, 3.0, 0)),
    ('random4', (1, [1, 0, 0, 0], 'fefc58a0461e28b3', 0.042064087, 2.92376, 0)),
    ('random5', (0, [0, 0, 0, 0], 'da39a3ee5e6b4b0d', 0.0, 0.0, 0)),
    ('random6', (1, [1, 0, 0, 0], '4de35015b68e8795', 0.032645798, 1.0, 0)),
    ('random7', (0, [0, 0, 0, 0], 'da39a3ee5e6b4b0d', 0.0, 0.0, 0)),
    ('random8', (1, [1, 0, 0, 0], '7ca72edf228115a1', 0.007431619, -3.353799, 0)),
    # the two corner vertices of the sunk wedge on the slope face (y = -4) lie on a face
    # of the base they are not inside: since the shortest-exit rule for vertex-face
    # contacts they are vertex-edge contacts, with the same plane, points and gaps
    # (keys: since vertex-edge ties within snap go to the first edge, a vertex on a seam
    # point between two collinear piece edges takes the first of them)
    ('l-block, base, sunk wedge',
     (8, [2, 2, 4, 0], '076fb1cd9776f765', 0.048654567, 37.830684, 4)),
    # 19 corner vertices just outside a neighbour's side face but below its top plane are
    # not inside it: vertex-edge (shortest exit) instead of vertex-face since that rule;
    # since vertex-edge ties within snap (5 µm here) go to the first edge, a few vertex-edge
    # contacts take the other of two edges equally near (keys, planes, gaps within snap)
    ('jittered boxes',
     (715, [143, 193, 373, 6], '18a0df01a6cc75a4', 0.49788554, 368121.784435, 1423)),
    ('random hulls', (3, [2, 1, 0, 0], '112dff058a5d8c66', 0.047108353, -2.240597, 0)),
])


@pytest.mark.parametrize("k", range(12))
def test_matches_recorded_contact_sets(k):
    name, blocks, search = regression_scenes()[k]
    assert digest(detect_contacts(blocks, search)) == RECORDED[name]


def test_cached_scene_matches_fresh_blocks():
    """Blocks moved with :meth:`Polyhedron.moved` reuse the cached topology; the result
    equals that of new blocks with their own topology arrays, and the cache follows a
    change of topology (same vertex count, other faces)."""
    blocks = jittered_boxes((2, 2, 2), seed=3)
    detect_contacts(blocks, 0.005)
    shift = np.random.default_rng(0).uniform(-1e-3, 1e-3, (len(blocks), 3))
    moved = [b.moved(b.vertices + d) for b, d in zip(blocks, shift, strict=True)]
    fresh = [Polyhedron.from_faces(b.vertices.copy(), [f.tolist() for f in b.faces])
             for b in moved]
    assert digest(detect_contacts(moved, 0.005)) == digest(detect_contacts(fresh, 0.005))
    flipped = BOX_FACES[1:] + BOX_FACES[:1]
    other = [Polyhedron.from_faces(b.vertices, flipped) for b in moved]
    again = [Polyhedron.from_faces(b.vertices, flipped) for b in moved]
    assert digest(detect_contacts(other, 0.005)) == digest(detect_contacts(again, 0.005))
    assert digest(detect_contacts(other, 0.005))[:2] == digest(detect_contacts(moved, 0.005))[:2]


#: two blocks of examples/block_system.json as they were at step 236 of a run: a vertex of
#: the upper block sits where three faces of the lower one meet, below the plane of one
#: of them but outside the block (the run blew up from this contact before the fix)
RIDGE_LOWER = (
    [
        [7.890230908846536, 10.01680244853255, 1.5061277512170255],
        [8.46042370286805, 10.009607718788967, 0.00034220327119438565],
        [8.657822207191595, 8.67792068013616, 3.0042080959625164],
        [9.99356650953426, 7.893654358086675, 1.5119804792940863],
        [9.995866913582997, 8.459701313100966, 0.004614717646525435],
        [10.003105125904426, 10.002361845405206, -4.656603403763171e-06],
        [10.003855649893554, 10.011357222376416, 2.9998951515598486],
    ],
    [[1, 5, 4], [4, 5, 6, 3], [5, 1, 0, 6], [3, 6, 2], [2, 6, 0], [3, 2, 0, 1, 4]],
)
RIDGE_UPPER = (
    [
        [5.7756865406509466, 9.999327041979361, 7.077997769223109],
        [6.342522540346598, 10.003172555093967, 5.583942127564249],
        [7.289870640524377, 7.3811735885124925, 9.991313265158155],
        [7.390572558353931, 7.280865593116523, 9.991169593598002],
        [8.666681349613135, 8.672714159778378, 2.994246685728059],
        [9.900512332517954, 10.002065764263238, 9.997164062544371],
        [10.010462086067752, 5.781116951565541, 7.071956009318027],
        [10.009945742002651, 6.350095458295744, 5.578709810002883],
        [10.001214250347507, 9.901757768867268, 9.997020390984218],
        [10.003798511886828, 10.015081409720304, 2.9972433442209074],
        [10.001017219471343, 10.002262620143778, 9.997204628428598],
    ],
    [[3, 8, 10, 5, 2],
     [9, 10, 8, 6, 7],
     [5, 10, 9, 1, 0],
     [1, 9, 4],
     [8, 3, 6],
     [9, 7, 4],
     [2, 5, 0],
     [0, 1, 4, 7, 6, 3, 2]],
)


def test_vertex_beyond_a_convex_edge_is_no_deep_vertex_face_contact():
    """A vertex outside a convex block but below the plane of one of its faces, whose
    projection grazes that face's boundary, is not a deep vertex-face penetration: the
    face it would exit by (shortest exit) is the one it is outside of. Before the rule
    this pair reported a vertex-face gap of -0.0135 m while touching."""
    lower = Polyhedron.from_faces(np.array(RIDGE_LOWER[0]), RIDGE_LOWER[1])
    upper = Polyhedron.from_faces(np.array(RIDGE_UPPER[0]), RIDGE_UPPER[1])
    assert lower.problems() == [] and upper.problems() == []
    c = detect_contacts([lower, upper], 0.3185770124393326)
    check_invariants(c)
    assert len(c) > 0
    assert c.gap.min() > -1e-4


def test_no_false_penetration_past_a_narrow_face():
    """Two cut blocks of a jointed cube (issue 12) that share a face and a corner: the
    larger one's face next to that corner is a 25 mm strip, so its far edge lies within a
    50 mm search of the thin block's corner. Measured on that edge's other face plane the
    corner is 26 mm deep, although the blocks only touch: no contact may be deeper than
    the pair's shallowest face exit (it was reported, and the run failed at step 1)."""
    thin = Polyhedron.from_faces(
        [[2.2198283011366393, 0.08211274048626203, 8.222243632302742],
         [2.232737713857535, 0.0, 8.178412214523119],
         [2.370047455242713, 0.0, 8.532916343141787],
         [3.554449384464093, 0.02474064703098653, 7.228328600977269],
         [3.5583390028304223, 0.0, 7.215122152992077],
         [3.5997105588813993, 0.0, 7.321934585085357]],
        [[2, 1, 4, 5], [4, 1, 0, 3], [5, 4, 3], [0, 1, 2], [2, 5, 3, 0]])
    thick = Polyhedron.from_faces(
        [[1.5723360151677324, 0.436044743106106, 6.883145533086392],
         [1.640889098650257, 0.0, 6.65038677734994],
         [2.2198283011366393, 0.08211274048626203, 8.222243632302742],
         [2.232737713857535, 0.0, 8.178412214523119],
         [2.906957098495185, 0.3786726496508305, 5.889230501760919],
         [2.9664903876231437, 0.0, 5.687096715818899],
         [3.554449384464093, 0.02474064703098653, 7.228328600977269],
         [3.5583390028304223, 0.0, 7.215122152992077]],
        [[7, 3, 1, 5], [4, 5, 1, 0], [2, 3, 7, 6], [7, 5, 4, 6], [0, 1, 3, 2], [4, 0, 2, 6]])
    for search in (0.01, 0.05, 0.1, 0.3):
        c = detect_contacts([thin, thick], search)
        check_invariants(c)
        assert len(c) and c.gap.min() > -1e-12, (search, c.gap.min())


def test_narrow_phase_in_slices_finds_the_same_contacts(monkeypatch):
    """On threads the narrow phase runs in slices of the piece pairs, joined in order: the
    contact set is the one of a single pass, array for array."""
    import dataclasses

    import numba

    import engine.contact.detection as det

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one numba thread: the narrow phase never runs in slices")
    blocks = jittered_boxes((4, 3, 2))
    monkeypatch.setattr(det, "THREADED_MIN_PAIRS", 10**12)
    whole = detect_contacts(blocks, 0.005)
    monkeypatch.setattr(det, "THREADED_MIN_PAIRS", 0)
    sliced = detect_contacts(blocks, 0.005)
    assert len(whole) == 715
    for f in dataclasses.fields(whole):
        np.testing.assert_array_equal(getattr(sliced, f.name), getattr(whole, f.name))
