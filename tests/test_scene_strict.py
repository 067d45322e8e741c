"""Issue 33's strict scene types where issue 32's fields are: the domain shapes, the
excavations and the stages take a number only as a JSON number, points and lengths within
±1e8 m, names printable (schemas/fields.py), as the rest of the scene does; coordinates
read from a terrain or mesh file obey the same bound; the service's duration and step
limits count a staged run's stages."""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import pytest
import trimesh

from schemas.convert import build_model
from schemas.errors import SceneError
from schemas.scene import load_scene
from tests.excavation_scenes import roof_wedge_scene
from tests.service_helpers import make_client

SLOPE = {"profile": [[0, 0], [10, 10], [20, 10]], "dip_direction": 180, "width": 10,
         "base": -5}
GRID = {"x0": 0, "y0": 0, "dx": 5, "dy": 5, "elevations": [[10, 11], [10, 11]]}


def _set(scene: dict[str, Any], path: str, value: Any) -> dict[str, Any]:
    """A copy of `scene` with the value at the dotted `path` (list indices as numbers)."""
    out = copy.deepcopy(scene)
    keys = [int(k) if k.isdigit() else k for k in path.split(".")]
    node = out
    for k in keys[:-1]:
        node = node[k]
    node[keys[-1]] = value
    return out


STAGED = roof_wedge_scene()
TUNNEL = {**roof_wedge_scene(), "excavations": [
    {"name": "tunnel", "tunnel": {"width": 4, "start": [0, -6, -3], "trend": 0,
                                  "length": 12}}]}
TUNNEL["stages"][1]["excavate"] = ["tunnel"]

#: (scene, the field set, the value, what the loc starts with, a word of the message)
CASES = [
    (STAGED, "stages.0.duration", "0.1", "stages[0]", "number"),
    (STAGED, "stages.1.duration", True, "stages[1]", "number"),
    (STAGED, "stages.0.name", "set\x00tle", "stages[0]", "printable"),
    (STAGED, "stages.1.drain", "yes", "stages[1]", "true or false"),
    (STAGED, "excavations.0.cavern.center", [1e155, 0, 0], "excavations[0]", "100000000"),
    (STAGED, "excavations.0.cavern.size", ["14", 6, 3], "excavations[0]", "number"),
    (TUNNEL, "excavations.0.tunnel.width", 1e155, "excavations[0]", "100000000"),
    (TUNNEL, "excavations.0.tunnel.start", [0, "-6", -3], "excavations[0]", "number"),
    (TUNNEL, "excavations.0.tunnel.length", 1e9, "excavations[0]", "100000000"),
    ({"domain": {"slope": SLOPE}}, "domain.slope.width", "10", "domain.slope.width",
     "number"),
    ({"domain": {"slope": SLOPE}}, "domain.slope.profile.1", [10, 1e155],
     "domain.slope.profile", "100000000"),
    ({"domain": {"slope": SLOPE}}, "domain.slope.base", False, "domain.slope.base", "number"),
    ({"domain": {"terrain": {"grid": GRID, "base": 0}}}, "domain.terrain.grid.dx", True,
     "domain.terrain.grid.dx", "number"),
    ({"domain": {"terrain": {"grid": GRID, "base": 0}}}, "domain.terrain.grid.elevations.0.1",
     "11", "domain.terrain.grid.elevations", "number"),
    ({"domain": {"terrain": {"file": "a.asc", "base": 0}}}, "domain.terrain.file", "a\x00.asc",
     "domain.terrain.file", "printable"),
]


@pytest.mark.parametrize(("scene", "path", "value", "loc", "word"), CASES,
                         ids=[f"{c[1]}={c[2]!r}" for c in CASES])
def test_issue_32_fields_are_strict(scene: dict[str, Any], path: str, value: Any, loc: str,
                                    word: str) -> None:
    load_scene(scene)  # the scene as written is valid
    with pytest.raises(SceneError) as info:
        load_scene(_set(scene, path, value))
    assert any(p["loc"].startswith(loc) and word in p["msg"] for p in info.value.problems), \
        info.value.problems


def test_file_coordinates_beyond_the_bound_are_refused() -> None:
    """An ESRI grid placed at 1e155 m and a mesh scaled to 1e155 m: a problem naming the
    field and the bound (the cutter would overflow on them), not a crash."""
    asc = ("ncols 2\nnrows 2\nxllcorner 1e155\nyllcorner 0\ncellsize 5\n"
           "11 11\n10 10\n")
    box = trimesh.creation.box(extents=(6, 4, 5))
    obj = "".join("v " + " ".join(repr(float(c) * 1e155) for c in v) + "\n"
                  for v in box.vertices)
    obj += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in box.faces)
    for domain, loc in (({"terrain": {"data": asc, "format": "asc", "base": 0}},
                         "domain.terrain.data"),
                        ({"mesh": {"data": obj, "format": "obj"}}, "domain.mesh.data")):
        with pytest.raises(SceneError) as info:
            build_model({"domain": domain})
        assert any(p["loc"] == loc and "within ±1e+08 m" in p["msg"]
                   for p in info.value.problems), info.value.problems


def test_a_fine_sampling_of_a_surface_mesh_is_refused_before_it_is_built() -> None:
    """A 10 m surface mesh sampled every 1e-9 m would be 1e20 nodes (arrays of 75 GiB):
    refused at grid_spacing from the node count, before any array is made."""
    text = trimesh.creation.box(extents=(10, 10, 1)).export(file_type="stl_ascii")
    with pytest.raises(SceneError) as info:
        build_model({"domain": {"terrain": {"data": text, "format": "stl",
                                            "grid_spacing": 1e-9, "base": -5}}})
    assert any(p["loc"] == "domain.terrain.grid_spacing" and "the limit is 40,000" in p["msg"]
               for p in info.value.problems), info.value.problems


@pytest.mark.parametrize("case", ["string-duration", "duration-limit", "steps-limit"])
def test_service_refuses_staged_scenes_over_its_limits(tmp_path: Path, case: str) -> None:
    """422 naming the field: a stage's duration as a string; stages that together last
    longer than POLYDDA_MAX_DURATION (each one shorter), or run more steps than
    POLYDDA_MAX_STEPS (2 stages of 0.6 s at Δt 2 ms = 600 steps > 500), though
    analysis.duration (unused by a staged run) is within both."""
    scene = roof_wedge_scene(settle=0.6, fall=0.6)
    settings: dict[str, Any] = {}
    if case == "string-duration":
        scene["stages"][0]["duration"] = "0.6"
        want = ("stages[0]", "number")
    elif case == "duration-limit":
        settings["max_duration"] = 1.0
        want = ("stages", "the stages last 1.2 s")
    else:
        settings["max_steps"] = 500
        want = ("analysis.time_step", "600 steps")
    scene["analysis"]["duration"] = 0.1
    with make_client(tmp_path / "data", **settings) as c:
        r = c.post("/jobs", json=scene)
        assert r.status_code == 422, r.text
        errors = r.json()["errors"]
        assert any(e["loc"].startswith(want[0]) and want[1] in e["msg"] for e in errors), errors
        assert c.get("/jobs").json()["numberMatched"] == 0
