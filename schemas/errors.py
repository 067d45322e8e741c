"""Scene errors: a list of problems, each a field path and a message a rock engineer can act on.

Every user mistake in a scene (bad JSON, bad values, unknown names, open block surfaces,
overlapping blocks, size limits) ends as one :class:`SceneError`; pydantic errors are
translated here into the same `{"loc": "blocks[0].faces", "msg": "..."}` form.
"""

from __future__ import annotations

import difflib
import math
import re
import types
import typing
from collections.abc import Sequence
from typing import Any

from pydantic import BaseModel, ValidationError

Loc = Sequence[str | int]

_IDENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_\-]*$")
#: characters of an input a message quotes at most (a value, a line of text)
ECHO_CHARS = 40
#: characters of a name or key a field path shows at most (the longest name a scene may
#: give: schemas.fields.Name)
NAME_CHARS = 100
#: characters of a field path and of a message at most (whatever they quote)
MAX_LOC_CHARS, MAX_MSG_CHARS = 200, 500
#: control characters and lone surrogates: written as escapes wherever input is echoed
_UNSAFE = re.compile(r"[\x00-\x1f\x7f\ud800-\udfff]")
_LONE_SURROGATE = re.compile(r"[\ud800-\udfff]")


def _escape(text: str) -> str:
    return _UNSAFE.sub(lambda m: m.group().encode("unicode_escape").decode("ascii"), text)


def echo(text: str, limit: int = ECHO_CHARS) -> str:
    """A short, printable excerpt of user input for a message: at most `limit` characters
    (then "…"), control characters and lone surrogates written as escapes (\\x00, \\ud800),
    so a reply stays small and valid UTF-8 whatever was sent."""
    return _escape(text[:limit]) + ("…" if len(text) > limit else "")


def bounded(text: str, limit: int) -> str:
    """`text` made printable (as :func:`echo`) and cut to about `limit` characters, saying
    how many more there were: the last guard on anything a reply repeats."""
    if len(text) <= limit and not _UNSAFE.search(text):
        return text
    safe = _escape(text[:limit])
    return safe if len(text) <= limit else f"{safe}… ({len(text) - limit:,} more characters)"


class SceneError(Exception):
    """A scene the engine cannot use; `problems` lists `{"loc": ..., "msg": ...}` dicts
    (each bounded and printable: :func:`bounded`)."""

    def __init__(self, problems: Sequence[dict[str, str]]):
        self.problems = [{"loc": bounded(str(p.get("loc", "")), MAX_LOC_CHARS),
                          "msg": bounded(str(p["msg"]), MAX_MSG_CHARS)} for p in problems]
        super().__init__("\n".join(self.lines()))

    def lines(self) -> list[str]:
        """One human-readable line per problem: `loc: msg` (or just `msg` at top level)."""
        return [f"{p['loc']}: {p['msg']}" if p["loc"] else p["msg"] for p in self.problems]


class Problems:
    """Collects problems while checking a scene; `raise_if_any()` turns them into a SceneError."""

    def __init__(self) -> None:
        self.items: list[dict[str, str]] = []

    def add(self, loc: str, msg: str) -> None:
        self.items.append({"loc": loc, "msg": msg})

    def __bool__(self) -> bool:
        return bool(self.items)

    def raise_if_any(self) -> None:
        if self.items:
            raise SceneError(self.items)


def fmt_num(value: Any) -> str:
    """A number as a person would write it: 95, 0.25, 1e+10."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return repr(value)
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, int) and abs(value) >= 10**15:  # exactly, beyond any float too
        digits = str(abs(value))
        mantissa = (digits[0] + "." + digits[1:10]).rstrip("0").rstrip(".")
        return f"{'-' if value < 0 else ''}{mantissa}e+{len(digits) - 1:02d}"
    return format(value, ".10g")


def fmt_count(n: float) -> str:
    """A large count rounded for a message: 4,630 / 46,000 / 4.63 million / 2.1e+12."""
    if n < 1e4:
        return f"{n:,.0f}"
    if n < 1e6:
        return f"{round(n, -3):,.0f}"
    if n < 1e9:
        return f"{n / 1e6:.3g} million"
    if n < 1e12:
        return f"{n / 1e9:.3g} billion"
    return f"{n:.2g}"


def fmt_point(p: Sequence[float]) -> str:
    """A point as `(0, 0, 99)`."""
    return "(" + ", ".join(fmt_num(float(x)) for x in p) + ")"


def format_loc(loc: Loc, data: Any = None) -> str:
    """Field path as `blocks[0] ('wedge').faces` or `materials.rock.density`.

    `data` (the raw input) lets list items that carry a `name` show it.
    """
    out = ""
    node = data
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
            item = node[part] if isinstance(node, list) and 0 <= part < len(node) else None
            if isinstance(item, dict) and isinstance(item.get("name"), str):
                out += f" ('{echo(item['name'], NAME_CHARS)}')"
            node = item
        else:
            key = str(part)
            if _IDENT.match(key) and len(key) <= NAME_CHARS:
                out += ("." if out else "") + key
            else:
                out += f"['{echo(key, NAME_CHARS)}']"
            node = node.get(key) if isinstance(node, dict) else None
    return out


def unicode_problems(data: Any, limit: int = 20) -> list[dict[str, str]]:
    """Strings of parsed JSON (values and keys, at any depth) holding a lone surrogate
    (`"\\ud800"` unpaired: valid JSON, but no text: it cannot be stored or written),
    each with its field path; at most `limit`."""
    problems: list[dict[str, str]] = []
    stack: list[tuple[list[str | int], Any]] = [([], data)]
    while stack and len(problems) < limit:
        path, node = stack.pop()
        if isinstance(node, dict):
            items: list[tuple[str | int, Any]] = list(node.items())
        elif isinstance(node, list):
            items = list(enumerate(node))
        else:
            items = []
        inner = []
        for key, value in items:
            if isinstance(key, str) and _LONE_SURROGATE.search(key):
                problems.append({"loc": format_loc([*path, key], data), "msg": (
                    "this name is not valid Unicode text (it holds a lone surrogate, "
                    f"{_escape(_LONE_SURROGATE.search(key).group())})")})
            elif isinstance(value, str):
                if found := _LONE_SURROGATE.search(value):
                    problems.append({"loc": format_loc([*path, key], data), "msg": (
                        "must be valid Unicode text: it holds a lone surrogate "
                        f"({_escape(found.group())}) at character {found.start() + 1:,}")})
            elif isinstance(value, dict | list):
                inner.append(([*path, key], value))
        stack.extend(reversed(inner))  # depth first, in the document's order
    return problems[:limit]


def _got(value: Any) -> str:
    if isinstance(value, str):
        return f"'{echo(value)}'"
    if isinstance(value, dict):
        return "an object"
    if isinstance(value, list):
        return f"a list of {len(value)}"
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    return fmt_num(value)


def _unwrap(tp: Any) -> Any:
    """The model or container inside `Annotated[...]` / `X | None`."""
    while True:
        origin = typing.get_origin(tp)
        if origin is typing.Annotated:
            tp = typing.get_args(tp)[0]
        elif origin in (typing.Union, types.UnionType):
            args = [a for a in typing.get_args(tp) if a is not type(None)]
            if len(args) != 1:
                return tp
            tp = args[0]
        else:
            return tp


def _model_at(root: type[BaseModel], loc: Loc) -> type[BaseModel] | None:
    """The pydantic model class that the path `loc` points into (None if unsure)."""
    tp: Any = root
    for part in loc:
        tp = _unwrap(tp)
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            if not isinstance(part, str) or part not in tp.model_fields:
                return None
            tp = tp.model_fields[part].annotation
            continue
        origin = typing.get_origin(tp)
        args = typing.get_args(tp)
        if origin is dict and len(args) == 2:
            tp = args[1]
        elif origin in (list, tuple) and args:
            tp = args[0]
        else:
            return None
    tp = _unwrap(tp)
    return tp if isinstance(tp, type) and issubclass(tp, BaseModel) else None


def _message(err: dict[str, Any], root: type[BaseModel] | None) -> str:
    kind = err["type"]
    ctx = err.get("ctx") or {}
    value = err.get("input")
    if kind in ("value_error", "assertion_error") and "error" in ctx:
        return str(ctx["error"])
    if kind == "missing":
        return "is required"
    if kind == "extra_forbidden":
        key = str(err["loc"][-1])
        model = _model_at(root, err["loc"][:-1]) if root is not None else None
        if model is None:
            return "unknown field"
        allowed = list(model.model_fields)
        close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
        hint = f"did you mean '{close[0]}'?" if close else "allowed: " + ", ".join(allowed)
        return f"unknown field ({hint})"
    if kind in ("float_type", "float_parsing", "int_type", "int_parsing"):
        whole = kind.startswith("int")
        return f"must be a {'whole ' if whole else ''}number, got {_got(value)}"
    if kind == "int_from_float":
        return f"must be a whole number, got {_got(value)}"
    if kind == "finite_number":
        return "must be a finite number"
    if kind in ("bool_type", "bool_parsing"):
        return f"must be true or false, got {_got(value)}"
    if kind in ("string_type",):
        return f"must be text, got {_got(value)}"
    if kind == "string_pattern_mismatch":
        from schemas.fields import MULTILINE

        if ctx.get("pattern") == MULTILINE:
            return ("must be printable text (no control characters such as NUL; tabs and "
                    "line breaks are fine)")
        return "must be printable text on one line (no control characters such as NUL)"
    if kind in ("string_too_short", "string_too_long"):
        lo, hi = ctx.get("min_length"), ctx.get("max_length")
        if kind == "string_too_short":
            return f"must have at least {lo} character{'s' if lo != 1 else ''}"
        return f"may have at most {hi:,} characters, got {len(value):,}" if isinstance(
            value, str) else f"may have at most {hi:,} characters"
    if kind in ("list_type", "tuple_type"):
        return f"must be a list [...], got {_got(value)}"
    if kind in ("dict_type", "model_type", "model_attributes_type"):
        return f"must be an object {{...}}, got {_got(value)}"
    if kind in ("too_short", "too_long"):
        lo, hi = ctx.get("min_length"), ctx.get("max_length")
        n = ctx.get("actual_length")
        if lo == hi == 3 or (kind == "too_short" and lo == 3 and hi is None):
            return f"must be 3 numbers [x, y, z], got {n}"
        if kind == "too_short":
            return f"needs at least {lo} items, got {n}"
        return f"may have at most {ctx.get('max_length')} items, got {n}"
    if kind == "literal_error":
        return f"must be one of {ctx.get('expected')}, got {_got(value)}"
    if kind == "greater_than":
        gt = ctx.get("gt")
        return (
            f"must be positive, got {_got(value)}"
            if gt == 0
            else f"must be greater than {fmt_num(gt)}, got {_got(value)}"
        )
    if kind == "greater_than_equal":
        ge = ctx.get("ge")
        return (
            f"must be zero or positive, got {_got(value)}"
            if ge == 0
            else f"must be at least {fmt_num(ge)}, got {_got(value)}"
        )
    if kind == "less_than":
        return f"must be less than {fmt_num(ctx.get('lt'))}, got {_got(value)}"
    if kind == "less_than_equal":
        return f"must be at most {fmt_num(ctx.get('le'))}, got {_got(value)}"
    return str(err.get("msg", kind))


def from_validation_error(
    exc: ValidationError, data: Any = None, root: type[BaseModel] | None = None
) -> SceneError:
    """Translate a pydantic ValidationError on `root` (input `data`) into a SceneError."""
    problems = []
    seen = set()
    for err in exc.errors(include_url=False):
        loc = format_loc(err["loc"], data)
        msg = _message(err, root)
        if (loc, msg) not in seen:
            seen.add((loc, msg))
            problems.append({"loc": loc, "msg": msg})
    return SceneError(problems)
