"""Reference checks of a scene's excavations and stages: names exist and are used once, a
stage names only bolts, excavations and joint materials the scene has."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from schemas.errors import Problems


def bolt_names(scene: Any) -> tuple[list[str], list[str]]:
    """The scene's bolt names (own or bolt<k+1>) and bolt pattern prefixes."""
    return ([b.name or f"bolt{k + 1}" for k, b in enumerate(scene.bolts)],
            [bp.name_prefix for bp in scene.bolt_patterns])


def stage_problems(scene: Any, p: Problems, joint_material: Callable[[str, str | None], None]
                   ) -> None:
    """Problems of `scene.excavations` and `scene.stages`, recorded in `p`."""
    known: dict[str, int] = {}
    for k, e in enumerate(scene.excavations):
        if e.name in known:
            p.add(f"excavations[{k}].name", f"excavation name '{e.name}' is used twice (also "
                  f"excavations[{known[e.name]}])")
        known.setdefault(e.name, k)
    if scene.excavations and scene.domain is None:
        p.add("excavations", "excavations are cut from a 'domain': give one")
    bolts, prefixes = bolt_names(scene)
    dug: dict[str, int] = {}
    names: dict[str, int] = {}
    for s, st in enumerate(scene.stages):
        loc = f"stages[{s}]"
        if st.name in names:
            p.add(f"{loc}.name", f"stage name '{st.name}' is used twice (also "
                  f"stages[{names[st.name]}])")
        names.setdefault(st.name, s)
        for k, name in enumerate(st.excavate):
            where = f"{loc}.excavate[{k}]"
            if name not in known:
                p.add(where, f"unknown excavation '{name}' (known: "
                      f"{', '.join(known) or 'none'})")
            elif scene.excavations[known[name]].cut == "before_joints":
                p.add(where, f"excavation '{name}' is cut before the joints: its rock is never "
                      "there to remove (make it 'after_joints')")
            elif name in dug:
                p.add(where, f"excavation '{name}' is already dug out by stages[{dug[name]}]")
            dug.setdefault(name, s)
        for field in ("add_bolts", "remove_bolts"):
            for k, name in enumerate(getattr(st, field)):
                if name not in bolts and name not in prefixes:
                    p.add(f"{loc}.{field}[{k}]", f"unknown bolt '{name}' (known: "
                          f"{', '.join(bolts + prefixes) or 'none'})")
        for name in st.joint_materials:
            joint_material(f"{loc}.joint_materials.{name}", name)
        if st.water is not None:
            for k, jp in enumerate(st.water.joint_pressures):
                joint_material(f"{loc}.water.joint_pressures[{k}].joint_material",
                               jp.joint_material)


def refuse_stages(scene: Any, analysis: str) -> None:
    """SceneError at `stages` (of a Scene or a BuildResult) for an analysis of one model (a
    factor-of-safety search, a critical seismic coefficient, a sweep): a staged scene's
    model is its rock before any stage, excavations still in place, which is not what its
    stages describe."""
    if getattr(scene, "stages", None):
        from schemas.errors import SceneError

        raise SceneError([{"loc": "stages", "msg": (
            f"{analysis} analyses one model, and a staged scene's is its rock before any "
            "stage (excavations still in place): run the stages (process 'simulation', "
            "polydda run), or write the scene as it stands at the stage to analyse")}])
