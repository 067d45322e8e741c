"""MkDocs hook: the reference pages are generated at build time, so they cannot drift from
the code. `<!-- generated: scene | cli | api | processes -->` in a page is replaced by the
Markdown made from the scene's JSON Schema (schemas.scene_json_schema), the argparse parser
(service.cli.main.build_parser) and the OpenAPI document (service.api.app.create_app); the
charts of benchmarks/results/ are added to the site as img/benchmarks/*.png, and the JSON
Schema and the OpenAPI document as downloadable files."""

from __future__ import annotations

import argparse
import json
import os
import re
import sys
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:  # mkdocs run from a checkout that is not installed
    sys.path.insert(0, str(ROOT))

MARKER = re.compile(r"<!--\s*generated:\s*([a-z]+)\s*-->")
#: the charts the validation and performance pages show, from benchmarks/results/
CHARTS = ROOT / "benchmarks" / "results"


def _cell(text: Any) -> str:
    """Text for one Markdown table cell (no pipes or line breaks)."""
    return " ".join(str(text).split()).replace("|", "\\|")


def _table(head: Iterable[str], rows: Iterable[Iterable[Any]]) -> str:
    head = list(head)
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(_cell(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


# --------------------------------------------------------------------------- scene schema


def _anchor(name: str) -> str:
    return name.lower()


def _type(spec: dict[str, Any]) -> str:
    """A schema node as a short readable type, linking the definitions it refers to."""
    if "$ref" in spec:
        name = spec["$ref"].rsplit("/", 1)[1]
        return f"[{name}](#{_anchor(name)})"
    if "anyOf" in spec:
        kinds = [s for s in spec["anyOf"] if s.get("type") != "null"]
        return " or ".join(_type(s) for s in kinds) or "null"
    if "enum" in spec:
        return "one of " + ", ".join(f"`{json.dumps(v)}`" for v in spec["enum"])
    if "const" in spec:
        return f"`{json.dumps(spec['const'])}`"
    kind = spec.get("type", "any")
    physical = ""
    if "x-physical-range" in spec:  # schemas.physical
        lo, hi = spec["x-physical-range"]
        unit = f" {spec['x-unit']}" if spec.get("x-unit") else ""
        what = "magnitude " if kind == "array" else ""
        physical = f"; physical {what}range {lo:g} – {hi:g}{unit}"
    if kind == "array":
        n = ""
        if spec.get("minItems") is not None and spec.get("minItems") == spec.get("maxItems"):
            n = f"{spec['minItems']} × "
        items = spec.get("items")
        text = f"array of {n}{_type(items) if items else 'any'}"
        return f"{text} ({physical[2:]})" if physical else text
    if kind == "object" and isinstance(spec.get("additionalProperties"), dict):
        return f"map of name → {_type(spec['additionalProperties'])}"
    bounds = []
    for key, sign in (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"),
                      ("exclusiveMaximum", "<")):
        if key in spec:
            bounds.append(f"{sign} {spec[key]:g}")
    if isinstance(kind, list):
        kind = " or ".join(kind)
    if not bounds and physical:
        return f"{kind} ({physical[2:]})"
    return f"{kind} ({', '.join(bounds)}{physical})" if bounds else str(kind)


def _default(spec: dict[str, Any], required: bool) -> str:
    if required:
        return "required"
    if "default" not in spec or spec["default"] is None:
        return "—"
    return f"`{json.dumps(spec['default'], ensure_ascii=False)}`"


def _fields(model: dict[str, Any]) -> str:
    required = set(model.get("required", ()))
    rows = [(f"`{name}`", _type(spec), _default(spec, name in required),
             spec.get("description", ""))
            for name, spec in model.get("properties", {}).items()]
    return _table(["field", "type", "default", "meaning"], rows)


def scene_markdown() -> str:
    """The scene format, one table per object of the JSON Schema."""
    from schemas import scene_json_schema

    schema = scene_json_schema()
    out = [f"Scene format version **{schema.get('x-schema-version', '?')}**. "
           "Units are SI (m, kg, s, N, Pa) and angles are degrees; axes are x = East, "
           "y = North, z = Up. A field left out takes its default; an unknown field is "
           "an error that names it.", "",
           "## Scene (the top level) {#scene}", "",
           " ".join(schema.get("description", "").split()), "", _fields(schema), ""]
    for name, model in sorted(schema.get("$defs", {}).items()):
        out += [f"## {name} {{#{_anchor(name)}}}", ""]
        if model.get("description"):
            out += [" ".join(model["description"].split()), ""]
        if model.get("properties"):
            out += [_fields(model), ""]
        elif "enum" in model:
            out += [_type(model), ""]
    return "\n".join(out)


# --------------------------------------------------------------------------- command line


def _subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str, Any]]:
    """(name, one-line help, sub-parser) of every subcommand, in the parser's order."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            helps = {a.dest: a.help or "" for a in action._choices_actions}
            return [(name, helps.get(name, ""), p) for name, p in action.choices.items()]
    return []


def _argument_rows(parser: argparse.ArgumentParser) -> list[tuple[str, str, str]]:
    rows = []
    for a in parser._actions:
        if isinstance(a, argparse._HelpAction):
            continue
        if a.option_strings:
            choices = "{" + ",".join(map(str, a.choices)) + "}" if a.choices else None
            meta = "" if a.nargs == 0 else f" {a.metavar or choices or a.dest.upper()}"
            name = ", ".join(f"`{o}{meta}`" for o in a.option_strings)
        else:
            name = f"`{a.metavar or a.dest}`"
        default = ("" if a.default in (None, False, argparse.SUPPRESS) or a.nargs == 0
                   else f"`{a.default}`")
        rows.append((name, _expand_help(a, parser.prog), default))
    return rows


def _expand_help(action: argparse.Action, prog: str) -> str:
    """An argument's help with argparse's `%(default)s`-style fields filled in."""
    text = action.help or ""
    if "%" not in text:
        return text
    try:
        return text % {**vars(action), "prog": prog}
    except (KeyError, TypeError, ValueError):
        return text


def cli_markdown() -> str:
    """Every `polydda` subcommand: its purpose, usage and arguments, from argparse."""
    from service.cli.main import build_parser

    old = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"  # argparse wraps usage lines to the terminal's width
    try:
        parser = build_parser()
        commands = _subcommands(parser)
        out = [" ".join((parser.description or "").split()), "",
               _table(["command", "what it does"],
                      ((f"[`{n}`](#{n})", h) for n, h, _ in commands)), "",
               "Exit codes: 0 done; 1 an unexpected error; 2 bad input (a scene, a file, an "
               "option), one problem per line; 3 a run that could not complete (it says why).",
               ""]
        for name, helptext, sub in commands:
            out += [f"## polydda {name} {{#{name}}}", "", helptext[:1].upper() + helptext[1:]
                    + ".", "", "```text", sub.format_usage().strip(), "```", ""]
            if sub.description and sub.description != helptext:
                out += [" ".join(sub.description.split()), ""]
            rows = _argument_rows(sub)
            if rows:
                out += [_table(["argument", "meaning", "default"], rows), ""]
        return "\n".join(out)
    finally:
        if old is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = old


# --------------------------------------------------------------------------- REST API


def _openapi() -> dict[str, Any]:
    from service.api.app import create_app

    return create_app(listen="127.0.0.1").openapi()  # the API as served on loopback


def _schema_type(spec: dict[str, Any]) -> str:
    if "$ref" in spec:
        return spec["$ref"].rsplit("/", 1)[1]
    if "anyOf" in spec:
        return " or ".join(_schema_type(s) for s in spec["anyOf"] if s.get("type") != "null")
    if "enum" in spec:
        return "one of " + ", ".join(f"`{v}`" for v in spec["enum"])
    return str(spec.get("type", "any"))


def api_markdown() -> str:
    """Every operation of the OpenAPI document, grouped by tag."""
    doc = _openapi()
    ops: dict[str, list[tuple[str, str, dict[str, Any]]]] = {}
    for path, item in doc["paths"].items():
        for method, op in item.items():
            if method in ("get", "post", "put", "delete", "patch"):
                ops.setdefault((op.get("tags") or ["other"])[0], []).append((method, path, op))
    out = [f"OpenAPI {doc.get('openapi', '')}, API version {doc['info'].get('version', '')}. "
           "The same document is served by a running server at `/openapi.json` and browsable "
           "at `/docs`; this copy: [openapi.json](openapi.json).", "",
           _table(["method", "path", "what it does"],
                  ((m.upper(), f"[`{p}`](#{o.get('operationId', '').lower()})",
                    o.get("summary", "")) for tag in ops for m, p, o in ops[tag])), ""]
    for tag, items in ops.items():
        out += [f"## {tag.capitalize()} {{#tag-{tag.lower()}}}", ""]
        for method, path, op in items:
            op_id = op.get("operationId", f"{method}-{path}").lower()
            out += [f"### {method.upper()} `{path}` {{#{op_id}}}", "",
                    _cell(op.get("summary", "")), ""]
            if op.get("description"):
                out += [" ".join(op["description"].split()), ""]
            params = op.get("parameters", [])
            if params:
                out += [_table(["parameter", "in", "type", "required", "meaning"],
                               ((f"`{p['name']}`", p.get("in", ""),
                                 _schema_type(p.get("schema", {})),
                                 "yes" if p.get("required") else "no",
                                 p.get("description", "")) for p in params)), ""]
            body = op.get("requestBody")
            if body:
                kinds = ", ".join(f"`{k}`" for k in body.get("content", {}))
                what = _cell(body.get("description", "")).rstrip(".")
                out += [f"Request body ({kinds}){': ' + what if what else ''}. A scene is the "
                        "JSON of the [scene reference](scene.md).", ""]
            responses = op.get("responses", {})
            if responses:
                out += [_table(["status", "meaning", "content"],
                               ((code, r.get("description", ""),
                                 ", ".join(f"`{k}`" for k in r.get("content", {})))
                                for code, r in responses.items())), ""]
    return "\n".join(out)


def processes_markdown() -> str:
    """The processes a job can run (service.jobs.processes)."""
    from service.jobs.processes import PROCESSES

    return _table(["process", "title", "what it does", "main result"],
                  ((f"`{p.id}`", p.title, p.description, f"`{p.main_artifact}`")
                   for p in PROCESSES.values()))


GENERATORS: dict[str, Callable[[], str]] = {
    "scene": scene_markdown, "cli": cli_markdown, "api": api_markdown,
    "processes": processes_markdown,
}


# --------------------------------------------------------------------------- the hooks


def on_files(files: Any, config: Any) -> Any:
    """Add the benchmark charts and the machine-readable references to the site."""
    from mkdocs.structure.files import File

    for png in sorted(CHARTS.glob("*.png")):
        files.append(File.generated(config, f"img/benchmarks/{png.name}",
                                    abs_src_path=str(png)))
    from schemas import scene_json_schema

    files.append(File.generated(config, "reference/scene.schema.json",
                                content=json.dumps(scene_json_schema(), indent=2)))
    files.append(File.generated(config, "reference/openapi.json",
                                content=json.dumps(_openapi(), indent=2)))
    return files


def on_page_markdown(markdown: str, page: Any, config: Any, files: Any) -> str:
    """Replace every `<!-- generated: NAME -->` marker by its generated Markdown."""
    def replace(match: re.Match[str]) -> str:
        name = match.group(1)
        if name not in GENERATORS:
            raise ValueError(f"{page.file.src_uri}: no generator named {name!r} "
                             f"(known: {', '.join(GENERATORS)})")
        return GENERATORS[name]()

    return MARKER.sub(replace, markdown)
