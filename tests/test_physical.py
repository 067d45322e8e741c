"""Issue 40: physical nonsense is refused, in the CLI and the API alike, naming the field and
the range (schemas.physical); `analysis.allow_unphysical` accepts up to 1,000 times beyond
each end, never more."""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from schemas.convert import build_model
from schemas.errors import SceneError
from tests.service_helpers import cube_scene, make_client

ROOT = Path(__file__).resolve().parents[1]


def _set(path: str, value: Any) -> Callable[[dict[str, Any]], None]:
    """A change of `scene` at the dotted `path` (lists by index)."""
    def change(scene: dict[str, Any]) -> None:
        *parents, last = path.split(".")
        node: Any = scene
        for part in parents:
            node = node[int(part)] if isinstance(node, list) else node.setdefault(part, {})
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value
    return change


#: the issue's probes (each 201 before) and more of the same kind: (change, loc, range text)
NONSENSE = {
    "density 1e200": (_set("materials.rock.density", 1e200), "materials.rock.density",
                      "100 to 30,000 kg/m³"),
    "density 1e308": (_set("materials.rock.density", 1e308), "materials.rock.density",
                      "100 to 30,000 kg/m³"),
    "density 1e-300": (_set("materials.rock.density", 1e-300), "materials.rock.density",
                       "100 to 30,000 kg/m³"),
    "gravity 1e300": (_set("gravity", [0, 0, -1e300]), "gravity", "0 to 100 m/s²"),
    "penalty 1e300": (_set("analysis.penalty", 1e300), "analysis.penalty",
                      "5e+06 to 5e+14 N/m"),
    "young 1e300": (_set("materials.rock.young_modulus", 1e300),
                    "materials.rock.young_modulus", "1e+06 to 1e+12 Pa"),
    "cohesion 1e300": (_set("joint_materials.j.cohesion", 1e300), "joint_materials.j.cohesion",
                       "0 to 1e+08 Pa"),
    "time step 1e-300": (_set("analysis.time_step", 1e-300), "analysis.time_step",
                         "1e-07 to 10 s"),
    "velocity 1e5": (_set("blocks.0.velocity", {"translation": [1e5, 0, 0]}),
                     "blocks[0] ('cube').velocity.translation", "0 to 1,000 m/s"),
    "model 3e5 m": (_set("blocks.1.vertices", [[3e5 * x for x in v] for v in
                                               cube_scene()["blocks"][1]["vertices"]]),
                    "blocks", "0 to 100,000 m"),
}


@pytest.mark.parametrize("case", sorted(NONSENSE))
def test_physical_nonsense_is_refused_naming_the_field_and_the_range(case: str) -> None:
    change, loc, text = NONSENSE[case]
    scene = cube_scene()
    change(scene)
    with pytest.raises(SceneError) as caught:
        build_model(scene)
    problems = caught.value.problems
    assert [p["loc"] for p in problems] == [loc], problems
    assert text in problems[0]["msg"] and "allow_unphysical" in problems[0]["msg"], problems


def test_the_service_answers_422_and_the_cli_exits_2(tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]
                                                      ) -> None:
    """The API refuses them at submission (201 before: then `successful`, "singular
    system" or infinite displacements), the CLI with exit code 2 and the same line."""
    from service.cli.main import main

    with make_client(tmp_path / "data") as c:
        for case in ("density 1e200", "gravity 1e300", "penalty 1e300"):
            change, loc, text = NONSENSE[case]
            scene = cube_scene()
            change(scene)
            r = c.post("/jobs", json=scene)
            assert r.status_code == 422, (case, r.text)
            errors = r.json()["errors"]
            assert errors[0]["loc"] == loc and text in errors[0]["msg"], errors
            path = tmp_path / "scene.json"
            path.write_text(json.dumps(scene))
            assert main(["validate", str(path)]) == 2
            assert capsys.readouterr().err.startswith(f"{loc}: "), case
        assert c.get("/jobs").json()["numberMatched"] == 0


def test_allow_unphysical_accepts_a_thousand_times_beyond_and_no_more() -> None:
    """A centrifuge model's 100 g passes with the override; 1e300 m/s² does not."""
    scene = cube_scene()
    scene["gravity"] = [0, 0, -981]
    with pytest.raises(SceneError, match="allow_unphysical: true"):
        build_model(scene)
    scene["analysis"]["allow_unphysical"] = True
    assert build_model(scene).model.gravity[2] == -981
    for change in (_set("gravity", [0, 0, -1e300]), _set("materials.rock.density", 1e-300),
                   _set("analysis.penalty", 1e300)):
        bad = copy.deepcopy(scene)
        change(bad)
        with pytest.raises(SceneError, match="beyond even what analysis.allow_unphysical"):
            build_model(bad)


def test_every_example_keeps_the_ranges() -> None:
    """Every shipped example builds (its penalty within the range of its derived one)."""
    for path in sorted((ROOT / "examples").glob("*.json")):
        build_model(path)


def test_the_schema_states_the_ranges() -> None:
    from schemas import scene_json_schema

    material = scene_json_schema()["$defs"]["MaterialSpec"]["properties"]
    assert material["density"]["x-physical-range"] == [100, 30_000]
    assert material["density"]["x-unit"] == "kg/m³"
