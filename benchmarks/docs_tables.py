"""The measured tables of docs/contact-solvers.md, made from the benchmarks' result files so
that the page says what the commands it cites measured (tests/test_docs.py holds the page
to them). Each table sits between `<!-- name -->` and `<!-- /name -->` in the page.

Run: `python -m benchmarks.docs_tables` after the benchmarks to write the tables into the
page.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
PAGE = ROOT / "docs" / "contact-solvers.md"


def _load(name: str) -> dict | list | None:
    path = RESULTS / name
    return json.loads(path.read_text()) if path.is_file() else None


def solvers_table() -> str:
    """Every solver on the same cases (`python -m benchmarks.bench_contact_solvers 10`)."""
    data = _load("contact_solvers.json")
    if not data:
        return "(not measured yet: `python -m benchmarks.bench_contact_solvers 10`)"
    lines = ["Measured in one run on this machine's 2 cores, shared with other work "
             "(`python -m benchmarks.bench_contact_solvers 10`, "
             "`benchmarks/results/contact_solvers.json`; REPORT.md section 7 has every phase):",
             "", "| case | solver | error | s per step | iterations per step (median) | "
             "Δt held | s per simulated s |", "|---|---|---|---|---|---|---|"]
    for r in data["accuracy"]:
        lines.append(f"| {r['case']} | {r['solver']} | {r['error']:.1e} | | | 1 ms | "
                     f"{r['wall_s']:.2g} (wall) |")
    for r in data["speed"]:
        if r.get("status") == "error":
            lines.append(f"| {r['case']} | {r['solver']} | | | | | failed |")
        elif r["solver"] == "MuJoCo":
            apart = " (run apart, after)" if r.get("note") else ""
            lines.append(f"| {r['case']} | MuJoCo{apart} | | {r['wall_s'] / r['steps']:.4f} | | "
                         f"1 ms | {r['per_sim_second_s']:.3g} |")
        else:
            its = r.get("iterations_median", r["iterations_mean"])
            lines.append(f"| {r['case']} ({r['blocks']}) | {r['solver']} | | "
                         f"{r['per_step_s']:.3g} | {its:.0f} | {r['mean_dt'] * 1e3:.2g} ms | "
                         f"{r['per_sim_second_s']:.3g}"
                         + (f" ({r['status']})" if r["status"] != "completed" else "") + " |")
    return "\n".join(lines)


def toppling_table() -> str:
    """T1 after 1 s at several Δt (`python -m benchmarks.bench_toppling_dt`)."""
    rows = _load("toppling_dt.json")
    if not rows:
        return "(not measured yet: `python -m benchmarks.bench_toppling_dt`)"
    solvers = list(dict.fromkeys(r["solver"] for r in rows))
    steps = sorted({r["dt"] for r in rows}, reverse=True)
    got = {(r["solver"], r["dt"]): r for r in rows}
    lines = ["| Δt | " + " | ".join(solvers) + " |", "|---" * (len(solvers) + 1) + "|"]
    for dt in steps:
        cells = []
        for s in solvers:
            r = got.get((s, dt))
            cells.append("" if r is None else f"{r['T1_rotation']:.3f} rad")
        lines.append(f"| {dt * 1e3:g} ms | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def sleeping_table() -> str:
    """Sleeping on and off on a slope where a tenth moves (`python -m
    benchmarks.bench_sleeping`)."""
    data = _load("sleeping.json")
    if not data:
        return "(not measured yet: `python -m benchmarks.bench_sleeping`)"
    lines = [f"Measured (`python -m benchmarks.bench_sleeping`, "
             f"`benchmarks/results/sleeping.json`): the standing 134-block mass beside 13 "
             f"cubes sliding down a ramp, Newton's method, the last {data['measured_s']:g} s "
             f"of {data['duration_s']:g} s:", "",
             "| sleeping | wall (s) | blocks asleep at the end |", "|---|---|---|"]
    for r in data["rows"]:
        lines.append(f"| {'on' if r['sleep_velocity'] > 0 else 'off'} | {r['wall_s']:.2f} | "
                     f"{r['asleep_end']} of {r['free_blocks']} |")
    r_on = next(r for r in data["rows"] if r["sleep_velocity"] > 0)
    if r_on["asleep_end"]:
        lines += ["", f"Sleeping costs {data['ratio_sleeping_to_awake']:.2f} of the run "
                      "without it."]
    else:
        lines += ["", f"No block slept, so the ratio of the two walls "
                      f"({data['ratio_sleeping_to_awake']:.2f}) is the machine's noise, not "
                      "a saving: see below why the standing mass stays awake."]
        if "blocks_not_holding_end" in r_on:
            lines += ["", f"At the end of the run with sleeping on, "
                          f"{r_on['contacts_not_holding_end']:,} of the standing mass's "
                          f"{r_on['contacts_end']:,} contacts, in "
                          f"{r_on['blocks_not_holding_end']} blocks, fail sleeping's holding "
                          "test."]
    return "\n".join(lines)


TABLES: dict[str, Callable[[], str]] = {"solvers-table": solvers_table,
                                        "toppling-table": toppling_table,
                                        "sleeping-table": sleeping_table}


def block(name: str, text: str) -> str:
    """A table as it stands in the page, between its markers."""
    return f"<!-- {name} -->\n{text}\n<!-- /{name} -->"


def render(page: str) -> str:
    """The page with every table made afresh from the result files."""
    for name, make in TABLES.items():
        page = re.sub(rf"<!-- {name} -->.*?<!-- /{name} -->", lambda _m, n=name, f=make:
                      block(n, f()), page, flags=re.S)
    return page


def main() -> None:
    PAGE.write_text(render(PAGE.read_text()))
    print(f"wrote the measured tables of {PAGE.relative_to(ROOT)}")


if __name__ == "__main__":
    main()
