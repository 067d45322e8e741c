"""A short, plain-text account of a result file (for the CLI and logs)."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from engine.results.reader import Result, open_result


def summarize(result: Result | str | os.PathLike[str]) -> dict[str, Any]:
    """Key numbers of a run as JSON-ready values: status, steps, time, largest motion, energies."""
    if not isinstance(result, Result):
        with open_result(result) as r:
            return summarize(r)
    out: dict[str, Any] = {
        "status": result.status, "message": result.message, "n_blocks": result.n_blocks,
        "n_steps": result.n_steps, "engine_version": result.engine_version,
    }
    if result.n_steps == 0:
        return out
    k = result.n_steps - 1
    out["final_time"] = float(result.times[k])
    disp = np.linalg.norm(result.centroids(k) - result.initial_centroids, axis=1)
    i = int(np.argmax(disp))
    out["max_displacement"] = {"block": result.block_names[i] or str(i), "index": i,
                               "value": float(disp[i])}
    out["final_energies"] = {name: float(v[k]) for name, v in result.energies().items()
                             if not np.isnan(v[k])}
    if result.contacts_recorded:
        out["final_contacts"] = int(len(result.contacts(k)["gap"]))
    pen = result.step_data()["max_penetration"]
    out["max_penetration"] = float(np.nanmax(pen)) if np.any(~np.isnan(pen)) else None
    return out


def format_summary(result: Result | str | os.PathLike[str]) -> str:
    """`summarize` as a few human-readable lines."""
    s = summarize(result)
    lines = [f"status: {s['status']}" + (f" ({s['message']})" if s["message"] else ""),
             f"blocks: {s['n_blocks']}, recorded steps: {s['n_steps']}"]
    if s["n_steps"]:
        md = s["max_displacement"]
        lines.append(f"final time: {s['final_time']:.6g} s")
        lines.append(f"largest displacement: {md['value']:.4g} m (block {md['block']})")
        if s.get("max_penetration") is not None:
            lines.append(f"largest penetration: {s['max_penetration']:.3g} m")
        if "final_contacts" in s:
            lines.append(f"contacts at the end: {s['final_contacts']}")
        for name, v in s["final_energies"].items():
            lines.append(f"{name}: {v:.6g} J")
    return "\n".join(lines)
