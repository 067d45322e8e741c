"""Numbers for people: lengths, angles, forces, volumes and durations with their units and as
many digits as mean something (the CLI's text and the reports; the JSON documents keep every
digit). No `7.151881302842081`, no Python `True` or `['cube']`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any


def number(x: float, digits: int = 4) -> str:
    """A plain number to `digits` significant digits, without an exponent in the range a
    rock engineer meets (1e-4 to 1e7): 0.0123, 12.35, 2801, 1.2e-05."""
    if not math.isfinite(x):
        return "–"
    if x == 0:
        return "0"
    ax = abs(x)
    if ax < 1e-4 or ax >= 1e7:
        return f"{x:.{digits - 1}e}".replace("e-0", "e-").replace("e+0", "e+")
    exponent = math.floor(math.log10(ax))
    decimals = max(0, digits - 1 - exponent)
    text = f"{x:.{decimals}f}"
    if decimals and abs(float(text)) >= 10.0 ** (exponent + 1):  # 0.99999 rounds to 1.0000
        text = f"{x:.{decimals - 1}f}"
    return text


def fixed(x: float, decimals: int) -> str:
    """`x` with `decimals` decimals and no negative zero (-0.0001 to 3 decimals is 0.000)."""
    text = f"{x:.{decimals}f}"
    return text[1:] if text.startswith("-") and not text.strip("-0.") else text


def length(x: float) -> str:
    """A length or displacement: 4.718 m, 12.3 mm, 2.5 µm (below 0.05 µm: 0 µm)."""
    if not math.isfinite(x):
        return "–"
    ax = abs(x)
    if ax >= 1.0:
        return f"{x:.3f} m"
    if ax >= 1e-3:
        return f"{x * 1e3:.1f} mm"
    return f"{x * 1e6:.1f} µm" if ax >= 5e-8 else "0 µm"


def lengths_unit(values: Sequence[float]) -> tuple[str, float]:
    """One unit for a column of lengths: (`m`, 1) when the largest is 1 m or more, else
    (`mm`, 1000)."""
    top = max((abs(v) for v in values if math.isfinite(v)), default=0.0)
    return ("m", 1.0) if top >= 1.0 else ("mm", 1e3)


def point(p: Sequence[float]) -> str:
    """A point or vector in m to the millimetre: (12.300, -4.250, 0.000) m."""
    return "(" + ", ".join(f"{x:.3f}" for x in p) + ") m"


def angle(x: float, decimals: int = 1) -> str:
    """An angle in degrees: 33.4°."""
    return f"{x:.{decimals}f}°" if math.isfinite(x) else "–"


def force(x: float) -> str:
    """A force: 512 N, 40.0 kN, 2.35 MN."""
    if not math.isfinite(x):
        return "–"
    ax = abs(x)
    if ax >= 1e6:
        return f"{x / 1e6:.2f} MN"
    if ax >= 1e3:
        return f"{x / 1e3:.1f} kN"
    return f"{x:.0f} N"


def stress(x: float) -> str:
    """A stress or pressure: 250 Pa, 20.0 kPa, 1.50 MPa, 10.0 GPa."""
    if not math.isfinite(x):
        return "–"
    for scale, unit, d in ((1e9, "GPa", 1), (1e6, "MPa", 2), (1e3, "kPa", 1)):
        if abs(x) >= scale:
            return f"{x / scale:.{d}f} {unit}"
    return f"{x:.0f} Pa"


def volume(x: float) -> str:
    """A volume: 29.77 m³ (four significant digits)."""
    return f"{number(x)} m³"


def seconds(x: float) -> str:
    """A (simulated) time or time step: 2.35 s, 0.100 s, 0.5 ms, 12 µs."""
    if not math.isfinite(x):
        return "–"
    if abs(x) >= 0.1 or x == 0:
        return f"{number(x, 3)} s"
    if abs(x) >= 1e-4:
        return f"{number(x * 1e3, 3)} ms"
    return f"{number(x * 1e6, 3)} µs"


def duration(x: float) -> str:
    """A wall-clock duration: 0.8 s, 42 s, 3 min 05 s, 1 h 02 min."""
    if not math.isfinite(x):
        return "–"
    if x < 10:
        return f"{x:.1f} s"
    if x < 60:
        return f"{x:.0f} s"
    m, s = divmod(int(round(x)), 60)
    if m < 60:
        return f"{m} min {s:02d} s"
    h, m = divmod(m, 60)
    return f"{h} h {m:02d} min"


def value(x: Any) -> str:
    """Any value of a scene or document for a table: yes / no, lists joined by commas,
    numbers to four significant digits, objects as `key value` pairs."""
    if isinstance(x, bool):
        return "yes" if x else "no"
    if x is None:
        return "–"
    if isinstance(x, int):
        return f"{x:,}" if abs(x) >= 10_000 else str(x)
    if isinstance(x, float):
        return number(x)
    if isinstance(x, list | tuple):
        if x and all(isinstance(v, int | float) and not isinstance(v, bool) for v in x):
            return "(" + ", ".join(number(float(v)) for v in x) + ")"
        return ", ".join(value(v) for v in x)
    if isinstance(x, dict):
        return "; ".join(f"{k} {value(v)}" for k, v in x.items())
    return str(x)


def plural(n: int, word: str, many: str | None = None) -> str:
    """`1 block`, `3 blocks`, `2 bodies` (with `many`)."""
    return f"{n:,} {word if n == 1 else (many or word + 's')}"


def trend_plunge(d: Sequence[float]) -> tuple[float, float] | None:
    """Trend (° clockwise from North, y) and plunge (° below horizontal) of a vector
    (x East, y North, z up); None for a zero vector."""
    dx, dy, dz = (float(x) for x in d)
    if dx == dy == dz == 0.0:
        return None
    return (math.degrees(math.atan2(dx, dy)) % 360.0,
            math.degrees(math.atan2(-dz, math.hypot(dx, dy))))


def direction(d: Sequence[float]) -> str:
    """A displacement's direction as geologists write it: 090/30 (trend/plunge, degrees;
    a negative plunge points up); – for none."""
    tp = trend_plunge(d)
    return "–" if tp is None else f"{tp[0]:03.0f}/{tp[1]:.0f}"
