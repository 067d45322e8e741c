"""`polydda.Scene`: the JSON document the command line runs, loaded, validated, cut into
blocks and saved from Python; every rule is the scene schema's (schemas.scene)."""

from __future__ import annotations

import copy
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from schemas.errors import SceneError

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["Blocks", "Scene", "SceneError"]


@dataclass
class Blocks:
    """The blocks a scene is cut into (what `polydda blocks` lists): a DataFrame, the
    warnings of the build and the engine's model behind them."""

    frame: pd.DataFrame
    warnings: list[str] = field(default_factory=list)
    build: Any = None

    def __len__(self) -> int:
        return len(self.frame)

    def _repr_html_(self) -> str:
        return f"<p>{len(self)} blocks</p>" + self.frame._repr_html_()


class Scene:
    """A scene as its JSON document (`data`, a dict you may edit) with its folder (files
    such as a terrain grid are read from it).

    `Scene.load(path | JSON text | dict)` checks it at once (SceneError naming every bad
    field); `Scene(dict)` only wraps it, and `validate()` says what is wrong.
    """

    def __init__(self, data: dict[str, Any] | None = None, base_dir: str | Path | None = None,
                 **fields: Any) -> None:
        self.data: dict[str, Any] = copy.deepcopy(dict(data or {}, **fields))
        self.base_dir = None if base_dir is None else Path(base_dir)

    # ------------------------------------------------------------------ in and out

    @classmethod
    def load(cls, source: str | Path | dict[str, Any] | Scene) -> Scene:
        """A scene from a file path, JSON text or a dict, checked against the schema
        (SceneError listing every problem with its field path)."""
        from schemas.scene import _parse, load_scene

        if isinstance(source, Scene):
            return source.copy()
        base = None
        if isinstance(source, Path) or (isinstance(source, str)
                                         and not source.lstrip().startswith(("{", "["))):
            base = Path(source).resolve().parent
        data = _parse(source)
        load_scene(data)  # raises SceneError
        return cls(data, base_dir=base)

    @classmethod
    def build_from(cls, **fields: Any) -> Scene:
        """A scene from its fields as keywords (`domain=`, `joints=`, `analysis=` ...),
        checked as :meth:`load` checks."""
        return cls.load(dict(fields))

    def save(self, path: str | Path) -> Path:
        """Write the scene as JSON (what `polydda run` reads) and return the path."""
        out = Path(path)
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(self.to_json() + "\n", encoding="utf-8")
        return out

    def to_json(self, indent: int | None = 2) -> str:
        """The scene's JSON text."""
        return json.dumps(self.data, indent=indent, ensure_ascii=False, allow_nan=False)

    def copy(self) -> Scene:
        """An independent copy (its data deep-copied)."""
        return Scene(self.data, base_dir=self.base_dir)

    @property
    def name(self) -> str:
        return str(self.data.get("name", "scene"))

    def __getitem__(self, key: str) -> Any:
        return self.data[key]

    def __setitem__(self, key: str, value: Any) -> None:
        self.data[key] = value

    def __eq__(self, other: object) -> bool:
        """Equal scenes mean the same (defaults filled in, as the schema reads them)."""
        if not isinstance(other, Scene):
            return NotImplemented
        return self.model() == other.model()

    def __repr__(self) -> str:
        return f"Scene({self.name!r})"

    # ------------------------------------------------------------------ checks

    def model(self) -> Any:
        """The validated pydantic model of the scene (SceneError if it is invalid)."""
        from schemas.scene import load_scene

        return load_scene(copy.deepcopy(self.data))

    def validate(self, *, cut: bool = True) -> list[dict[str, str]]:
        """Every problem of the scene as `{"loc", "msg"}` (empty: valid): the schema's
        field checks, and with `cut` the blocks' (cutting, overlaps, selections)."""
        try:
            if cut:
                self.build()
            else:
                self.model()
        except SceneError as exc:
            return list(exc.problems)
        return []

    def build(self) -> Blocks:
        """Cut the domain into blocks and resolve the scene (SceneError on a problem)."""
        import pandas as pd

        from schemas.convert import build_model

        built = build_model(self.model(), base_dir=self.base_dir)
        rows = []
        for name, source, b in zip(built.block_names, built.block_sources, built.model.blocks,
                                   strict=True):
            c = b.polyhedron.centroid
            rows.append({"block": name, "volume": float(b.polyhedron.volume),
                         "x": float(c[0]), "y": float(c[1]), "z": float(c[2]),
                         "fixed": bool(b.fixed), "concave": not b.polyhedron.is_convex,
                         "source": source,
                         "excavation": built.excavated[len(rows)]})
        frame = pd.DataFrame(rows, columns=["block", "volume", "x", "y", "z", "fixed",
                                            "concave", "source", "excavation"])
        return Blocks(frame.set_index("block"), list(built.warnings), built)
