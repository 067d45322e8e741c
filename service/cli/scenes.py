"""Scene commands: `polydda blocks` (with --export to OBJ / VTK), `contacts`, `validate`,
`schema`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from schemas.errors import SceneError
from schemas.scene import SCHEMA_VERSION, scene_json_schema
from service import readable as rd
from service.cli.common import EXIT_IO, EXIT_OK, EXIT_SCENE, load_scene, print_json
from service.documents import blocks_document, scene_contacts_document, surface

if TYPE_CHECKING:
    from schemas.convert import BuildResult

# --------------------------------------------------------------------------- export


def write_obj(path: Path, result: BuildResult) -> None:
    """Wavefront OBJ: one object per block (named), polygon faces."""
    lines = [f"# PolyDDA blocks, scene format {SCHEMA_VERSION}"]
    base = 1
    for name, block in zip(result.block_names, result.model.blocks, strict=True):
        verts, faces = surface(block.polyhedron)
        lines.append(f"o {name}")
        lines.extend(f"v {x:.9g} {y:.9g} {z:.9g}" for x, y, z in verts)
        lines.extend("f " + " ".join(str(base + i) for i in f) for f in faces)
        base += len(verts)
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_vtk(path: Path, result: BuildResult) -> None:
    """Legacy VTK polydata (ASCII): polygon faces with cell data `block` and `fixed`."""
    points, polys, block_of, fixed = [], [], [], []
    base = 0
    for k, block in enumerate(result.model.blocks):
        verts, faces = surface(block.polyhedron)
        points.append(verts)
        for f in faces:
            polys.append(f"{len(f)} " + " ".join(str(base + i) for i in f))
            block_of.append(k)
            fixed.append(int(block.fixed))
        base += len(verts)
    pts = np.vstack(points) if points else np.zeros((0, 3))
    size = sum(len(p.split()) for p in polys)
    lines = [
        "# vtk DataFile Version 3.0",
        f"PolyDDA blocks: {', '.join(result.block_names)[:200]}",
        "ASCII",
        "DATASET POLYDATA",
        f"POINTS {len(pts)} double",
        *(f"{x:.9g} {y:.9g} {z:.9g}" for x, y, z in pts),
        f"POLYGONS {len(polys)} {size}",
        *polys,
        f"CELL_DATA {len(polys)}",
        "SCALARS block int 1",
        "LOOKUP_TABLE default",
        *map(str, block_of),
        "SCALARS fixed int 1",
        "LOOKUP_TABLE default",
        *map(str, fixed),
    ]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")


EXPORTERS = {".obj": write_obj, ".vtk": write_vtk}


# --------------------------------------------------------------------------- commands


def cmd_blocks(args: argparse.Namespace) -> int:
    """List the blocks of a scene (name, volume, concave, fixed) and the total volume."""
    if args.export is not None and Path(args.export).suffix.lower() not in EXPORTERS:
        print(f"--export: unknown file type '{Path(args.export).suffix}' "
              f"(use {' or '.join(EXPORTERS)})", file=sys.stderr)
        return EXIT_SCENE
    result = load_scene(args.scene)
    blocks = result.model.blocks
    if args.export is not None:
        out = Path(args.export)
        try:
            EXPORTERS[out.suffix.lower()](out, result)
        except OSError as exc:
            print(f"--export: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
            return EXIT_IO
    if args.json:
        print_json(blocks_document(result))
        return EXIT_OK
    width = max([len(n) for n in result.block_names] + [5])
    print(rd.plural(len(blocks), "block"))
    print(f"{'name':<{width}}  {'volume (m³)':>12}  {'shape':<7}  {'fixed':<5}  "
          "centroid x, y, z (m)")
    for name, b in zip(result.block_names, blocks, strict=True):
        shape = "convex" if b.polyhedron.is_convex else "concave"
        c = ", ".join(f"{x:.3f}" for x in b.polyhedron.centroid)
        print(f"{name:<{width}}  {rd.number(b.polyhedron.volume, 6):>12}  {shape:<7}  "
              f"{'yes' if b.fixed else 'no':<5}  {c}")
    total = sum(b.polyhedron.volume for b in blocks)
    print(f"total volume: {rd.volume(total)}")
    if args.export is not None:
        print(f"written: {args.export}")
    return EXIT_OK


def cmd_contacts(args: argparse.Namespace) -> int:
    """The contact constraints of the scene as given (before any step)."""
    result = load_scene(args.scene)
    if args.search_distance is not None and not args.search_distance > 0:
        print("--search-distance: must be positive", file=sys.stderr)
        return EXIT_SCENE
    doc = scene_contacts_document(result, args.search_distance)
    rows, search = doc["contacts"], doc["search_distance"]
    if args.json:
        print_json(doc)
        return EXIT_OK
    print(f"{rd.plural(len(rows), 'contact constraint')} (search distance "
          f"{rd.length(search)})")
    for k, c in enumerate(rows, 1):
        pt = ", ".join(f"{x:.3f}" for x in c["point_i"])
        nm = ", ".join(f"{x:.3f}" for x in c["normal"])
        print(f"{k:>4}  {c['block_i']} / {c['block_j']}  {c['type']:<13} ({pt})  "
              f"n=({nm})  {c['mode']:<7} gap={rd.length(c['gap'])}")
    return EXIT_OK


def cmd_schema(args: argparse.Namespace) -> int:
    """Print the JSON Schema of the scene format."""
    print_json(scene_json_schema())
    return EXIT_OK


def cmd_validate(args: argparse.Namespace) -> int:
    """Check a scene completely (including cutting and overlaps); print `ok` or the problems
    (with --json: one document `{"valid", "blocks", "fixed", "warnings", "problems"}`)."""
    if not args.json:
        result = load_scene(args.scene, service_limits=args.service_limits)
        n, w = len(result.model.blocks), len(result.warnings)
        print(f"ok: {n} block{'s' if n != 1 else ''}, "
              f"{sum(b.fixed for b in result.model.blocks)} fixed"
              + (f" ({w} warning{'s' if w != 1 else ''})" if w else ""))
        return EXIT_OK
    try:
        result = load_scene(args.scene, quiet=True, service_limits=args.service_limits)
    except SceneError as exc:
        print_json({"valid": False, "problems": exc.problems})
        return EXIT_SCENE
    print_json({"valid": True, "blocks": len(result.model.blocks),
                 "fixed": sum(b.fixed for b in result.model.blocks),
                 "warnings": result.warnings, "problems": []})
    return EXIT_OK
