"""Polyhedron geometry: mass properties against closed forms and trimesh, edge convexity,
validation of bad surfaces in a rock engineer's words, the dip convention and the exact
rotation."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from engine.geometry.polyhedron import (
    Polyhedron,
    dip_normal,
    normal_to_dip,
    polyhedron_problems,
    rotation_matrix,
)
from engine.geometry.shapes import HEXAHEDRON_FACES, box, convex_hull, prism

L_BASE = [(0, 0), (3, 0), (3, 1), (1, 1), (1, 3), (0, 3)]  # L in plan, reflex corner (1, 1)


def test_box_mass_properties_are_exact() -> None:
    """A 2 × 1 × 0.5 m box: V = 1 m³, centroid at its centre, C = V diag(a², b², c²) / 12."""
    b = box([1, 2, 3], [3, 3, 3.5])
    assert b.volume == pytest.approx(1.0, rel=1e-14)
    np.testing.assert_allclose(b.centroid, [2, 2.5, 3.25], rtol=1e-14)
    np.testing.assert_allclose(b.second_moments, np.diag([4, 1, 0.25]) / 12, atol=1e-14)


def test_rotated_box_second_moments_rotate() -> None:
    """Rotating and moving a block turns C into R C Rᵀ; volume and centroid follow."""
    b = box([0, 0, 0], [2, 1, 0.5])
    rot = Rotation.from_rotvec([0.3, -0.7, 1.1]).as_matrix()
    moved = b.moved(b.vertices @ rot.T + [5, -2, 7])
    assert moved.volume == pytest.approx(b.volume, rel=1e-12)
    np.testing.assert_allclose(moved.centroid, rot @ b.centroid + [5, -2, 7], atol=1e-12)
    np.testing.assert_allclose(moved.second_moments, rot @ b.second_moments @ rot.T,
                               atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_mass_properties_match_trimesh(seed: int) -> None:
    """Random convex hulls and an L-shaped (concave) prism: volume, centroid and
    C = ½ tr(I)·1 − I (I the unit-density inertia tensor about the centroid, docs/theory.md)
    agree with trimesh."""
    rng = np.random.default_rng(seed)
    block = convex_hull(rng.normal(size=(15, 3)) * [2.0, 1.0, 0.5]) if seed else prism(
        np.array(L_BASE, float), 2.0)
    tris = [f[[0, k, k + 1]] for f in block.faces for k in range(1, len(f) - 1)]
    mesh = trimesh.Trimesh(block.vertices, np.array(tris), process=False)
    assert block.volume == pytest.approx(mesh.volume, rel=1e-12)
    np.testing.assert_allclose(block.centroid, mesh.center_mass, atol=1e-12)
    inertia = mesh.moment_inertia  # density 1, about the centre of mass
    expected = 0.5 * np.trace(inertia) * np.eye(3) - inertia
    np.testing.assert_allclose(block.second_moments, expected, atol=1e-10)


def test_edge_convexity_of_cube_and_l_prism() -> None:
    """Every edge of a cube is convex; the L prism has exactly one concave (reflex) edge,
    the vertical one at its inner corner; no edge is flat."""
    assert np.all(box([0, 0, 0], [1, 1, 1]).edge_convexity == 1)
    lp = prism(np.array(L_BASE, float), 2.0)
    concave = np.flatnonzero(lp.edge_convexity == -1)
    assert len(concave) == 1
    a, b = lp.vertices[lp.edges[concave[0]]]
    np.testing.assert_allclose(a[:2], [1, 1])
    np.testing.assert_allclose(b[:2], [1, 1])
    assert not lp.is_convex and box([0, 0, 0], [1, 1, 1]).is_convex
    assert np.all(lp.edge_convexity != 0)


def _cube() -> tuple[np.ndarray, list[list[int]]]:
    b = box([0, 0, 0], [1, 1, 1])
    return b.vertices.copy(), [list(f) for f in HEXAHEDRON_FACES]


def test_valid_cube_has_no_problems() -> None:
    v, f = _cube()
    assert polyhedron_problems(v, f) == []


def test_open_surface_names_the_edge() -> None:
    v, f = _cube()
    problems = polyhedron_problems(v, f[:-1])  # the last face (3, 0, 4, 7) left out
    assert problems and all("faces are not closed" in p for p in problems)
    assert any("edge (0, 3) has one face" in p for p in problems)


def test_non_manifold_edge_is_named() -> None:
    """Two cubes sharing only the edge (1, 2)-(5, 6) counted as one block: that edge has
    four faces."""
    v, f = _cube()
    v2 = v + [1, 1, 0]  # the second cube's edge 0-4 is the first's 2-6
    faces = f + [[i + 8 for i in face] for face in f]
    verts = np.vstack([v, v2])
    # merge the shared vertices so the edge is really shared
    remap = np.arange(16)
    remap[8], remap[12] = 2, 6
    faces = [[int(remap[i]) for i in face] for face in faces]
    problems = polyhedron_problems(verts, faces)
    assert any("not manifold: edge (2, 6) has 4 faces" in p for p in problems)


def test_flipped_face_is_an_orientation_problem() -> None:
    v, f = _cube()
    f[2] = f[2][::-1]
    problems = polyhedron_problems(v, f)
    assert problems and all("not consistently oriented" in p for p in problems)


def test_inside_out_block_has_negative_volume() -> None:
    v, f = _cube()
    problems = polyhedron_problems(v, [face[::-1] for face in f])
    assert problems == ["volume is not positive: faces must run counter-clockwise seen "
                        "from outside"]


def test_warped_face_is_not_planar() -> None:
    """Lifting one top corner by 1 cm warps the top face (the side faces through it stay
    planar: the corner moves within them); its vertices lie 2.5 mm off the mean plane."""
    v, f = _cube()
    v[6, 2] += 0.01
    assert polyhedron_problems(v, f) == [
        "face 1 is not planar: a vertex is 0.0025 m off its plane"]


def test_degenerate_inputs() -> None:
    v, f = _cube()
    assert polyhedron_problems(v[:3], f) == ["needs at least 4 vertices, each [x, y, z]"]
    assert polyhedron_problems(v, f[:3]) == ["needs at least 4 faces to enclose a volume"]
    bad = [list(face) for face in f]
    bad[0] = [0, 3, 99]
    assert polyhedron_problems(v, bad) == [
        "face 0 refers to a vertex index outside 0..7"]
    v[0, 0] = np.nan
    assert polyhedron_problems(v, f) == ["vertex coordinates must be finite numbers"]


@pytest.mark.parametrize(("dip", "ddir", "normal"), [
    (0.0, 123.0, (0, 0, 1)),
    (90.0, 0.0, (0, 1, 0)),     # vertical, dipping north: normal points north
    (90.0, 90.0, (1, 0, 0)),    # dipping east
    (45.0, 180.0, (0, -np.sqrt(0.5), np.sqrt(0.5))),
])
def test_dip_convention(dip: float, ddir: float, normal: tuple[float, ...]) -> None:
    """docs/theory.md: upward normal (sin δ sin α, sin δ cos α, cos δ); x East, y North."""
    np.testing.assert_allclose(dip_normal(dip, ddir), normal, atol=1e-15)
    if 0 < dip < 90:
        np.testing.assert_allclose(normal_to_dip(dip_normal(dip, ddir)), (dip, ddir))


def test_exact_rotation_matches_scipy_and_keeps_length() -> None:
    rng = np.random.default_rng(4)
    # angles from 0.1 to ~5 rad, tiny (1e-9) and zero rotations
    rv = rng.normal(size=(50, 3)) * np.repeat([0.1, 1.0, 3.0, 1e-9, 0.0], 10)[:, None]
    r = rotation_matrix(rv).reshape(-1, 3, 3)
    np.testing.assert_allclose(r, Rotation.from_rotvec(rv).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(np.einsum("nij,nkj->nik", r, r), np.repeat(np.eye(3)[None],
                               50, axis=0), atol=1e-14)


def test_polyhedron_from_faces_keeps_tags_and_moves() -> None:
    v, f = _cube()
    p = Polyhedron.from_faces(v, f, [3, 3, -1, -1, 5, -1])
    q = p.moved(v + 2.0)
    assert q.face_tags.tolist() == [3, 3, -1, -1, 5, -1]
    np.testing.assert_allclose(q.centroid, p.centroid + 2.0)


def test_width_is_the_thinnest_extent() -> None:
    """A cube is as wide as its side, a plate as its thickness, an L prism as its arms."""
    from engine.geometry.cutting.cut import convex_decomposition

    assert box([0, 0, 0], [1, 1, 1]).width == pytest.approx(1.0)
    assert box([0, 0, 0], [5, 5, 0.05]).width == pytest.approx(0.05)
    assert convex_decomposition(prism(np.array(L_BASE, float), 2.0)).width == pytest.approx(1.0)
