"""Domain shapes and excavation solids against their analytic sizes: tunnel sections,
bench prisms, a closed mesh as the domain (and the refused ones), a terrain from an ESRI
ASCII grid, a CSV of x y z and a surface mesh, all giving the same rock."""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from engine.geometry.excavations import section_prism, tunnel, tunnel_section
from schemas.convert import build_model
from schemas.errors import SceneError


def _area(sec: np.ndarray) -> float:
    return 0.5 * float(np.sum(sec[:, 0] * np.roll(sec[:, 1], -1)
                              - np.roll(sec[:, 0], -1) * sec[:, 1]))


@pytest.mark.parametrize("sides", [12, 24])
def test_tunnel_sections_have_their_polygon_areas(sides: int) -> None:
    """Circular: n triangles ½ r² sin(2π/n); D-shaped (width w, height h): the walls'
    rectangle w (h − w/2) plus the crown's n/2 triangles ½ r² sin(2π/n); both counter-
    clockwise, invert at w = 0, span w."""
    w, h, r = 6.0, 7.0, 3.0
    circ = tunnel_section("circular", w, sides=sides)
    assert _area(circ) == pytest.approx(sides / 2 * r**2 * math.sin(2 * math.pi / sides),
                                        rel=1e-12)
    d = tunnel_section("d_shaped", w, h, sides=sides)
    half = sides // 2
    assert _area(d) == pytest.approx(w * (h - r) + half / 2 * r**2 * math.sin(math.pi / half),
                                     rel=1e-12)
    for sec in (circ, d, tunnel_section("horseshoe", w, sides=sides)):
        assert sec[:, 1].min() == pytest.approx(0.0, abs=1e-12)
        assert np.ptp(sec[:, 0]) == pytest.approx(w, rel=1e-12)


def test_tunnel_prism_along_trend_and_plunge() -> None:
    """A straight tunnel's solid: section area × length, its axis along trend 45° plunge
    10°; a bent axis gives one prism per segment."""
    sec = tunnel_section("circular", 4.0, sides=16)
    t = tunnel("T", sec, np.array([[0, 0, 0], [10 * math.sin(math.radians(45))
                                               * math.cos(math.radians(10)),
                                               10 * math.cos(math.radians(45))
                                               * math.cos(math.radians(10)),
                                               -10 * math.sin(math.radians(10))]]))
    assert t.volume == pytest.approx(_area(sec) * 10.0, rel=1e-12)
    bent = tunnel("B", sec, np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0]]))
    assert len(bent.solids) == 2 and bent.volume == pytest.approx(2 * _area(sec) * 10, rel=1e-12)


def test_bench_prism_volume() -> None:
    """A concave (L-shaped) bench section is cut into triangles: the solids' volumes add
    up to its area × width."""
    sec = np.array([[0, 10], [20, 10], [20, 20], [10, 20], [10, 15], [0, 15]], float)
    b = section_prism("bench", sec, [0, 0], 90.0, 12.0)
    assert b.volume == pytest.approx(abs(_area(sec)) * 12.0, rel=1e-12)


def _mesh_text(mesh: trimesh.Trimesh) -> str:
    return mesh.export(file_type="stl_ascii")


JOINTS = [{"dip": 60, "dip_direction": 30, "point": [0.3, 0.2, 0.1], "spacing": 2.0},
          {"dip": 20, "dip_direction": 200, "point": [0.1, 0.2, 0.3], "spacing": 2.5}]


def test_a_closed_mesh_is_the_domain() -> None:
    """A box exported as STL gives the blocks of the same box written as `box`."""
    text = _mesh_text(trimesh.creation.box(extents=(6, 4, 5)))
    a = build_model({"domain": {"mesh": {"data": text, "format": "stl"}}, "joints": JOINTS})
    b = build_model({"domain": {"box": {"min": [-3, -2, -2.5], "max": [3, 2, 2.5]}},
                     "joints": JOINTS})
    va = sorted(x.polyhedron.volume for x in a.model.blocks)
    vb = sorted(x.polyhedron.volume for x in b.model.blocks)
    assert np.allclose(va, vb, rtol=1e-9) and sum(va) == pytest.approx(120.0, rel=1e-12)


def test_a_self_intersecting_mesh_is_refused() -> None:
    two = trimesh.util.concatenate([trimesh.creation.box(extents=(2, 2, 2)),
                                    trimesh.creation.box(extents=(2, 2, 2)).apply_translation(
                                        [1, 0.5, 0.5])])
    with pytest.raises(SceneError) as info:
        build_model({"domain": {"mesh": {"data": _mesh_text(two), "format": "stl"}}})
    assert any(p["loc"] == "domain.mesh.data" and "intersects itself" in p["msg"]
               for p in info.value.problems), info.value.problems


def _plane(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 10.0 + 0.3 * x + 0.1 * y


def test_terrain_grid_csv_and_surface_mesh_agree() -> None:
    """The same planar ground z = 10 + 0.3 x + 0.1 y as an ESRI ASCII grid, a CSV of x y z
    and a two-triangle surface mesh sampled every 5 m: one volume, ∫∫ (z − base) over the
    20 × 10 m footprint = 200 (10 + 0.3·10 + 0.1·5 + 2) = 3,100 m³, and the same blocks."""
    x, y = np.arange(0, 21, 5.0), np.arange(0, 11, 5.0)
    z = _plane(*np.meshgrid(x, y))
    asc = "\n".join(["ncols 5", "nrows 3", "xllcenter 0", "yllcenter 0", "cellsize 5"]
                    + [" ".join(f"{v:.6f}" for v in row) for row in z[::-1]])
    csv = "x,y,z\n" + "\n".join(f"{a},{b},{_plane(a, b)}" for b in y for a in x)
    v = np.array([[0, 0, 0], [20, 0, 0], [20, 10, 0], [0, 10, 0]], float)
    v[:, 2] = _plane(v[:, 0], v[:, 1])
    stl = _mesh_text(trimesh.Trimesh(v, [[0, 1, 2], [0, 2, 3]], process=False))
    volumes = []
    for spec in ({"data": asc, "format": "asc"}, {"data": csv, "format": "csv"},
                 {"data": stl, "format": "stl", "grid_spacing": 5.0}):
        built = build_model({"domain": {"terrain": {**spec, "base": -2}}, "joints": JOINTS})
        volumes.append(sorted(b.polyhedron.volume for b in built.model.blocks))
    assert sum(volumes[0]) == pytest.approx(3100.0, rel=1e-12)
    for other in volumes[1:]:
        assert np.allclose(other, volumes[0], rtol=1e-9)


def test_terrain_footprint_and_bad_grids() -> None:
    """A footprint crops the grid; a ragged grid, a hole and an overhanging profile are
    refused naming the field."""
    g = {"x0": 0, "y0": 0, "dx": 5, "dy": 5,
         "elevations": [[10, 11, 12, 13], [10, 11, 12, 13], [10, 11, 12, 13]]}
    built = build_model({"domain": {"terrain": {"grid": g, "base": 0,
                                                "footprint": [5, 0, 15, 10]}}})
    assert built.model.blocks[0].polyhedron.volume == pytest.approx(10 * 10 * 12, rel=1e-12)
    bad = [({"terrain": {"grid": {**g, "elevations": [[1, 2], [1]]}, "base": 0}},
            "domain.terrain.grid.elevations", "as many values"),
           ({"terrain": {"grid": {**g, "elevations": [[10, None], [10, 10]]}, "base": 0}},
            "domain.terrain.grid.elevations", "without an elevation"),
           ({"slope": {"profile": [[0, 5], [10, 15], [8, 20]], "dip_direction": 90,
                       "width": 5, "base": 0}}, "domain.slope.profile", "no overhang")]
    for domain, loc, text in bad:
        with pytest.raises(SceneError) as info:
            build_model({"domain": domain})
        assert any(p["loc"] == loc and text in p["msg"] for p in info.value.problems), \
            info.value.problems


def test_an_uncut_terrain_is_one_block_of_convex_pieces() -> None:
    """Without joints a hilly terrain is one concave block made of its columns' convex
    pieces (the contact search needs them), its volume kept."""
    g = {"x0": 0, "y0": 0, "dx": 5, "dy": 5,
         "elevations": [[10, 14, 11], [12, 9, 13], [10, 12, 11]]}
    built = build_model({"domain": {"terrain": {"grid": g, "base": 0}}})
    (block,) = built.model.blocks
    poly = block.polyhedron
    assert not poly.is_convex and len(poly.pieces) > 1
    # the volume under the two triangles of each cell, summed: 25/2 × the mean of each
    # triangle's three heights, over the 4 cells
    z = np.array(g["elevations"], float)
    vol = sum(12.5 * (z[j, i] + z[j, i + 1] + z[j + 1, i + 1]) / 3
              + 12.5 * (z[j, i] + z[j + 1, i + 1] + z[j + 1, i]) / 3
              for j in range(2) for i in range(2))
    assert poly.volume == pytest.approx(vol, rel=1e-12)
