"""Issue 40: a fuzz test of submissions. A scene that uses most of the format (materials,
joints, bolts and a bolt pattern, water, seismic, ground motion, loads, stages, a sweep)
with random unicode (surrogates and control characters included) in its string fields and
keys, and huge numbers in its number fields: every answer is below 500, a problem document
when it is an error, and small (a reply stays within 1 MB whatever the request)."""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tests.service_helpers import box, make_client

PROBLEM = "application/problem+json"


def rich_scene() -> dict[str, Any]:
    """A small valid scene touching most fields of the format (a cube on a slab)."""
    return {
        "schema_version": "1.0", "name": "fuzz", "description": "a cube\non a slab",
        "materials": {"rock": {"density": 2600.0, "young_modulus": 1e10,
                               "poisson_ratio": 0.25}},
        "joint_materials": {"joint": {"friction_angle": 35.0, "cohesion": 1000.0,
                                      "tensile_strength": 0.0},
                            "wet": {"friction_angle": 30.0}},
        "default_joint_material": "joint",
        "blocks": [box("cube", [0, 0, 0], [1, 1, 1], material="rock",
                       velocity={"translation": [0.0, 0.0, 0.0], "spin": [0.0, 0.0, 0.0]}),
                   box("base", [-1, -1, -1], [2, 2, 0], fixed=True)],
        "block_pairs": [{"blocks": ["cube", "base"], "joint_material": "joint"}],
        "boundary": {"point_loads": [{"point": [0.5, 0.5, 1.0], "force": [10.0, 0.0, 0.0],
                                      "block": "cube"}]},
        "gravity": [0.0, 0.0, -9.81],
        "seismic": {"kh": 0.05, "azimuth": 90.0, "kv": 0.0},
        "water": {"unit_weight": 9810.0,
                  "phreatic_surface": {"point": [0, 0, 0.5], "dip": 0.0,
                                       "dip_direction": 0.0},
                  "joint_pressures": [{"joint_material": "wet", "pressure": 100.0}]},
        "ground_motion": {"time": [0.0, 0.001, 0.002],
                          "acceleration": [[0, 0, 0], [0.1, 0, 0], [0, 0, 0]], "scale": 1.0},
        "bolts": [{"name": "b1", "head": [0.5, 0.5, 1.0], "anchor": [0.5, 0.5, -0.5],
                   "pretension": 1000.0, "capacity": 1e5}],
        "bolt_patterns": [{"origin": [0.2, 0.2, 1.0], "face_normal": [0, 0, 1],
                           "row_direction": [1, 0, 0], "spacing": 0.5, "rows": 1,
                           "columns": 1, "length": 1.5, "trend": 0.0, "plunge": 90.0,
                           "name_prefix": "p"}],
        "analysis": {"duration": 0.002, "time_step": 0.001, "record_interval": 1,
                     "penalty": 1e10, "contact_damping": 0.5},
        "sweep": {"n": 2, "seed": 1, "mode": "dda",
                  "parameters": {"cohesion": {"distribution": "uniform", "low": 0.0,
                                              "high": 2000.0}}},
        "stages": [{"name": "dry", "duration": 0.001},
                   {"name": "shake", "duration": 0.001, "drain": True,
                    "joint_materials": {"joint": {"friction_angle": 30.0}}}],
    }


def _leaves(node: Any, path: tuple[Any, ...] = ()) -> Iterator[tuple[tuple[Any, ...], Any]]:
    """(path, value) of every string and number, and (path + (KEY,), key) of every key."""
    if isinstance(node, dict):
        for k, v in node.items():
            yield (*path, k, KEY), k
            yield from _leaves(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            yield from _leaves(v, (*path, i))
    elif isinstance(node, str | int | float) and not isinstance(node, bool):
        yield path, node


KEY = object()  # marks a key's path in _leaves
LEAVES = list(_leaves(rich_scene()))
STRINGS = [p for p, v in LEAVES if isinstance(v, str)]
NUMBERS = [p for p, v in LEAVES if not isinstance(v, str)]

#: any code point: surrogates (Cs) and control characters (Cc) included
TEXT = st.text(st.characters(exclude_categories=()), max_size=60) | st.sampled_from(
    ["cu\ud800be", "\x00", "a\udc00", "\u202e", "x" * 5000, "", "名前", "\n\t\r"])
HUGE = st.sampled_from([1e308, -1e308, 1.7976931348623157e308, 5e-324, 1e200, -1e-300,
                        10**400, -(10**400), 2**63, 1e155, 0, -1]) | st.floats(
    allow_nan=False, allow_infinity=False) | st.integers(-(10**500), 10**500)


def _replace(scene: dict[str, Any], path: tuple[Any, ...], value: Any) -> None:
    """Put `value` at `path` (a key's path renames the key)."""
    *parents, last = path
    if last is KEY:
        *parents, key = parents
    node: Any = scene
    for part in parents:
        node = node[part]
    if last is KEY:
        node[value if value not in node else f"{value}_"] = node.pop(key)
    else:
        node[last] = value


@st.composite
def mutated_scene(draw: st.DrawFn) -> str:
    """The rich scene with 1 to 3 fields changed, as JSON text (surrogates escaped)."""
    scene = rich_scene()
    for _ in range(draw(st.integers(1, 3))):
        strings = draw(st.booleans())
        path = draw(st.sampled_from(STRINGS if strings else NUMBERS))
        value = draw(TEXT if strings else HUGE)
        try:
            _replace(scene, path, value)
        except KeyError:  # a key renamed by an earlier change
            continue
    return json.dumps(scene, ensure_ascii=True)


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    data = tmp_path_factory.mktemp("fuzz") / "data"
    with make_client(data, max_workers=1, client_quota=100_000) as c:
        yield c


def test_the_rich_scene_is_accepted(client: Any) -> None:
    """The fuzz starts from a valid scene (else it would fuzz one refusal)."""
    r = client.post("/jobs", json=rich_scene(), params={"process": "simulation"})
    assert r.status_code == 201, r.text
    assert len(STRINGS) > 40 and len(NUMBERS) > 80, (len(STRINGS), len(NUMBERS))


@given(text=mutated_scene())
@settings(max_examples=150, deadline=None, derandomize=True, database=None,
          suppress_health_check=list(HealthCheck))
def test_no_submission_gets_a_5xx(client: Any, text: str) -> None:
    r = client.post("/jobs", content=text.encode(), params={"process": "simulation"},
                    headers={"Content-Type": "application/json"})
    assert r.status_code < 500, (r.status_code, r.text[:2000], text[:2000])
    assert len(r.content) < max(64_000, 4 * len(text)), (len(r.content), len(text))
    if r.status_code >= 400:
        assert r.headers["content-type"] == PROBLEM, r.headers
        doc = r.json()
        assert doc["status"] == r.status_code and doc["detail"], doc


def test_the_service_logged_no_traceback(client: Any, tmp_path: Path) -> None:
    """Nothing the fuzz sent broke a check (an error there is logged and answered 503)."""
    r = client.get("/health")
    assert r.status_code == 200 and r.json()["status"] == "ok"


def test_mutations_reach_strings_keys_and_numbers() -> None:
    """The leaves are real: a key, a name and a number are among them."""
    assert ("materials", "rock", KEY) in STRINGS
    assert ("blocks", 0, "name") in STRINGS
    assert ("materials", "rock", "density") in NUMBERS
    scene = rich_scene()
    _replace(scene, ("materials", "rock", KEY), "r\ud800")
    assert "r\ud800" in scene["materials"] and copy.deepcopy(scene)
