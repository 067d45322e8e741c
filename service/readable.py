"""Numbers for people, the one formatter of the CLI's text and the reports (the JSON documents
keep every digit): lengths, angles, azimuths, forces, stresses, energies, volumes and
durations in engineering units (mm, kN, MN, kPa, kJ) with the significant figures that fit
the quantity; round-off noise (below NOISE of the quantity's scale) shown as 0, never
`1.56179e-13`; no negative zero (`-0.00°`); azimuths in [0, 360) after rounding (never
`360.00°`). No `7.151881302842081`, no Python `True` or `['cube']`."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

#: a value smaller than this fraction of its scale (the largest of the quantities it stands
#: with: the components of a vector, the forces on a block) is round-off: shown as 0
NOISE = 1e-9
#: engineering units, largest first: (factor, name)
FORCE_UNITS = ((1e6, "MN"), (1e3, "kN"), (1.0, "N"))
STRESS_UNITS = ((1e9, "GPa"), (1e6, "MPa"), (1e3, "kPa"), (1.0, "Pa"))
ENERGY_UNITS = ((1e6, "MJ"), (1e3, "kJ"), (1.0, "J"))


def denoised(x: float, scale: float | None = None) -> float:
    """`x`, or 0.0 when it is round-off against `scale` (|x| <= NOISE |scale|); no -0.0."""
    if scale is not None and math.isfinite(x) and abs(x) <= NOISE * abs(scale):
        return 0.0
    return x + 0.0


def number(x: float, digits: int = 4, scale: float | None = None) -> str:
    """A plain number to `digits` significant digits, without an exponent in the range a
    rock engineer meets (1e-4 to 1e7): 0.0123, 12.35, 2801, 1.2e-05; 0 when it is round-off
    against `scale`."""
    x = denoised(x, scale)
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


def quantity(x: float, units: Sequence[tuple[float, str]], digits: int = 4,
             scale: float | None = None) -> str:
    """`x` in the largest of `units` it reaches, to `digits` significant digits: 2.551 kN,
    3.500 MN, 20.0 kPa; `0 N` (the smallest unit) for zero or round-off against `scale`."""
    x = denoised(x, scale)
    if not math.isfinite(x):
        return "–"
    if x == 0:
        return f"0 {units[-1][1]}"
    factor, name = next(((f, n) for f, n in units if abs(x) >= f), units[-1])
    return f"{number(x / factor, digits)} {name}"


def vector(values: Sequence[float], units: Sequence[tuple[float, str]],
           digits: int = 4) -> str:
    """A vector in one unit (its largest component's), every component with the same
    decimals, round-off against the largest shown as 0: `[2.551, 0, -1.2] kN`."""
    xs = [float(v) for v in values]
    top = max((abs(v) for v in xs if math.isfinite(v)), default=0.0)
    if top == 0.0:
        return "[" + ", ".join("0" if math.isfinite(v) else "–" for v in xs) + f"] {units[-1][1]}"
    factor, name = next(((f, n) for f, n in units if top >= f), units[-1])
    decimals = max(0, digits - 1 - math.floor(math.log10(top / factor)))
    shown = [fixed(denoised(v, top) / factor, decimals) if math.isfinite(v) else "–"
             for v in xs]
    return "[" + ", ".join("0" if t.strip("-0.") == "" else t for t in shown) + f"] {name}"


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
    """An angle in degrees: 33.4° (no -0.0°)."""
    return f"{fixed(x, decimals)}°" if math.isfinite(x) else "–"


def degrees(x: float) -> str:
    """An angle as a scene gives it, to at most two decimals without trailing zeros: 40°,
    38.5°, 33.93°."""
    if not math.isfinite(x):
        return "–"
    text = fixed(x, 2).rstrip("0").rstrip(".")
    return f"{text or '0'}°"


def azimuth(x: float, decimals: int = 2) -> str:
    """An azimuth (trend, dip direction) in [0, 360) after rounding: 172.59°, 0.00° for
    359.999°, never 360.00°."""
    if not math.isfinite(x):
        return "–"
    r = round(x % 360.0, decimals)
    return f"{fixed(0.0 if r >= 360.0 else r, decimals)}°"


def force(x: float, scale: float | None = None) -> str:
    """A force to four significant digits: 512.0 N, 40.00 kN, 2.350 MN (0 N for round-off
    against `scale`)."""
    return quantity(x, FORCE_UNITS, 4, scale)


def forces(values: Sequence[float]) -> str:
    """A force vector in one unit: [1148, -418, 1025] kN."""
    return vector(values, FORCE_UNITS)


def stress(x: float, scale: float | None = None) -> str:
    """A stress or pressure to three significant digits: 250 Pa, 20.0 kPa, 1.50 MPa,
    10.0 GPa."""
    return quantity(x, STRESS_UNITS, 3, scale)


def energy(x: float, scale: float | None = None) -> str:
    """An energy to four significant digits: 1.234 kJ, 0 J for round-off against `scale`
    (the run's largest energy)."""
    return quantity(x, ENERGY_UNITS, 4, scale)


def area(x: float) -> str:
    """An area: 97.57 m²."""
    return f"{number(x)} m²"


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
