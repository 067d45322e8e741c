"""The scene's shared field types and model base, one definition for schemas/scene.py,
domains.py and stages.py (which scene.py imports, so they cannot import it).

Strict JSON types (a number is a JSON number, never "0.05" or true; a flag true or false),
no NaN or infinity, unknown fields refused; points and lengths within ±MAX_COORDINATE m
(1e155 coordinates overflowed in cutting and the engine), lengths within the physical size
of a model (schemas.physical); names printable, on one line.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from schemas.physical import physical

#: the largest coordinate (m) of a point, and the longest length: far beyond any rock mass
#: (the Earth's circumference is 4e7 m), far below where squares of lengths overflow
MAX_COORDINATE = 1e8
#: a coordinate (m): within ±MAX_COORDINATE
Coordinate = Annotated[float, Field(ge=-MAX_COORDINATE, le=MAX_COORDINATE)]
#: a point (m): each coordinate within ±MAX_COORDINATE
Point = Annotated[list[Coordinate], Field(min_length=3, max_length=3)]
#: a point of a section or a plan (m): two coordinates within ±MAX_COORDINATE
Point2 = Annotated[list[Coordinate], Field(min_length=2, max_length=2)]
#: a length (m): positive, at most MAX_COORDINATE; physically at most 1e5 m, a model's
#: largest size (schemas.physical)
Length = physical(0, 1e5, "m", "a length", Field(gt=0, le=MAX_COORDINATE))
#: control characters (NUL, newlines...) that no name or label may hold
PRINTABLE = r"^[^\x00-\x1f\x7f]*$"
Name = Annotated[str, Field(min_length=1, max_length=100, pattern=PRINTABLE)]
#: the scene's own name: one line of text
Label = Annotated[str, Field(max_length=200, pattern=PRINTABLE)]
#: control characters but the tab and line breaks: what no text of several lines may hold
MULTILINE = r"^[^\x00-\x08\x0b\x0c\x0e-\x1f\x7f]*$"
#: text of several lines (a description): printable, tabs and line breaks allowed
Text = Annotated[str, Field(max_length=20_000, pattern=MULTILINE)]
#: a file's path, relative to the scene: one line of text
FilePath = Annotated[str, Field(min_length=1, max_length=1000, pattern=PRINTABLE)]


class StrictModel(BaseModel):
    """A part of the scene: strict JSON types, finite numbers, no unknown fields."""

    # strict: a number is a JSON number (never "0.05" or true), a flag true or false
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, strict=True)
