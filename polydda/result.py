"""`polydda.open_result`: a result file (what `polydda run --out` writes) as pandas
DataFrames (blocks, histories, contacts, energies), its plots and report, and in Jupyter
the service's 3-D viewer inline, self-contained."""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import pandas as pd

__all__ = ["Result", "open_result"]

#: frames the inline viewer carries at most (every k-th recorded step beyond)
INLINE_FRAMES = 300


class Result:
    """A result file, open for reading (also one still being written). Close it with
    :meth:`close` or use it in a `with` block."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        from engine.results.reader import Result as EngineResult

        self.path = Path(path)
        #: the engine's reader behind it (inner layout: may change)
        self.engine = EngineResult(self.path)

    def close(self) -> None:
        self.engine.close()

    def __enter__(self) -> Result:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __getattr__(self, name: str) -> Any:
        """The reader's other methods (bolts(), water_resultants(), stages(), vertices(k),
        block_index(name) ...: docs/results.md) are the result's too."""
        if name.startswith("_") or name == "engine":
            raise AttributeError(name)
        return getattr(self.engine, name)

    def __repr__(self) -> str:
        return (f"Result({str(self.path)!r}: {self.status}, {self.engine.n_blocks} blocks, "
                f"{self.engine.n_steps} recorded steps)")

    # ------------------------------------------------------------------ what the run was

    @property
    def status(self) -> str:
        """'completed', 'failed', 'cancelled', 'stopped' or 'running'."""
        return self.engine.status

    @property
    def message(self) -> str:
        return self.engine.message

    @property
    def summary(self) -> dict[str, Any] | None:
        """The run's summary (None while it runs)."""
        return self.engine.summary

    @property
    def block_names(self) -> list[str]:
        return list(self.engine.block_names)

    @property
    def times(self) -> np.ndarray:
        """Time (s) of each recorded step."""
        return np.asarray(self.engine.times)

    @property
    def scene(self) -> Any:
        """The scene the run was made of (a :class:`polydda.Scene`; None if not stored)."""
        import json

        from polydda.scene import Scene

        text = self.engine.scene_json
        return None if not text else Scene(json.loads(text))

    # ------------------------------------------------------------------ tables

    def blocks(self) -> pd.DataFrame:
        """One row per block: fixed, volume (m³), initial centroid, final displacement
        `ux uy uz` and its magnitude `u` (m)."""
        import pandas as pd

        r = self.engine
        c0 = np.asarray(r.initial_centroids, float)
        last = (r.centroids(-1) - c0) if r.n_steps else np.zeros_like(c0)
        return pd.DataFrame({
            "fixed": np.asarray(r.fixed, bool), "volume": np.asarray(r.volume, float),
            "x": c0[:, 0], "y": c0[:, 1], "z": c0[:, 2],
            "ux": last[:, 0], "uy": last[:, 1], "uz": last[:, 2],
            "u": np.linalg.norm(last, axis=1)},
            index=pd.Index(self.block_names, name="block"))

    def history(self, block: str | int | None = None) -> pd.DataFrame:
        """Block motion over the recorded steps: one block's (`block` by name or index),
        or every block's (a `block` column): step, time (s), centroid `x y z`,
        displacement `ux uy uz u` (m), velocity `vx vy vz` (m/s)."""
        import pandas as pd

        r = self.engine
        names = self.block_names
        which = range(r.n_blocks) if block is None else [r.block_index(block)]
        centroid = r.history("centroid")
        velocity = r.history("velocity")
        steps, times = np.asarray(r.steps), np.asarray(r.times)
        parts = []
        for b in which:
            c = centroid[:, b, :]
            d = c - r.initial_centroids[b]
            v = velocity[:, b, :3]
            parts.append(pd.DataFrame({
                "block": names[b], "step": steps, "time": times,
                "x": c[:, 0], "y": c[:, 1], "z": c[:, 2],
                "ux": d[:, 0], "uy": d[:, 1], "uz": d[:, 2], "u": np.linalg.norm(d, axis=1),
                "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2]}))
        frame = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
        return frame.drop(columns="block") if block is not None else frame

    def contacts(self, step: int = -1) -> pd.DataFrame:
        """The contacts of one recorded step (default: the last), one row each: the two
        blocks, the contact point, normal, mode (open, locked, sliding), forces."""
        import pandas as pd

        c = self.engine.contacts(step)
        names = self.block_names
        cols: dict[str, Any] = {}
        for key, value in c.items():
            a = np.asarray(value)
            if key in ("block_i", "block_j"):
                cols[key] = [names[int(k)] if 0 <= int(k) < len(names) else int(k) for k in a]
            elif key == "mode":
                cols[key] = [("open", "locked", "sliding")[int(m)] if 0 <= int(m) < 3
                             else int(m) for m in a]
            elif a.ndim == 2:
                for j in range(a.shape[1]):
                    cols[f"{key}_{'xyz'[j] if a.shape[1] == 3 else j}"] = a[:, j]
            else:
                cols[key] = a
        return pd.DataFrame(cols)

    def energies(self) -> pd.DataFrame:
        """Energy and work terms (J) at each recorded step, indexed by time (s)."""
        import pandas as pd

        e = self.engine.energies()
        return pd.DataFrame(e, index=pd.Index(self.times, name="time"))

    # ------------------------------------------------------------------ pictures

    def plot(self, out: str | Path | None = None) -> list[Path]:
        """The PNG plots `polydda plot` makes (histories, energy, snapshots)."""
        from engine.results.plots import plot_all

        return list(plot_all(self.engine, out))

    def report(self, out: str | Path | None = None) -> Path:
        """The printable report `polydda report` writes (HTML with its figures inline)."""
        from service.api.local import write_report

        return write_report(self.path, Path(out) if out else self.path.with_suffix(".html"))

    def viewer_html(self, max_frames: int = INLINE_FRAMES) -> str:
        """The service's 3-D viewer of this result as one self-contained HTML page (its
        scripts and the frames inline: it opens offline, from a file or a notebook)."""
        from service.api.local import standalone_viewer

        return standalone_viewer(self.path, max_frames=max_frames)

    def _repr_html_(self) -> str:
        """Jupyter shows the viewer inline, in a frame of its own."""
        from html import escape

        page = self.viewer_html()
        return (f'<iframe srcdoc="{escape(page, quote=True)}" style="width:100%;height:560px;'
                'border:1px solid #ccd" title="PolyDDA viewer"></iframe>')


def open_result(path: str | os.PathLike[str]) -> Result:
    """Open a result file (`polydda run --out`, :func:`polydda.run`) for reading."""
    return Result(path)
