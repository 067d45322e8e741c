"""Progress of the long commands (`run`, `fos`, `seismic`, `sweep`) on stderr, with the time
elapsed and an estimate of the time left: a tqdm bar on a terminal, plain lines in a log
(one per tenth of the work, and one per event the command reports, such as a trial)."""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence
from typing import IO, Any


def clock(seconds: float | None) -> str:
    """A duration as 0:42, 12:05 or 1:02:05 ('?' when unknown)."""
    if seconds is None or not math.isfinite(seconds) or seconds < 0:
        return "?"
    s = int(round(seconds))
    h, m = divmod(s, 3600)
    m, s = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


#: done within this fraction of the total is done (a clock summed from time steps ends at
#: 1.9999999999998905 s of 2 s)
DONE_EPS = 1e-9
#: the tqdm bar counts in these steps of the whole (its percentage never goes back)
BAR_STEPS = 1000


class Progress:
    """Work `done` of `total` (any unit: simulated seconds, trials, realisations).

    On a terminal a tqdm bar (elapsed, remaining, a note such as the step); otherwise one
    plain line each time another tenth is done (unless `tenths` is false: work made of a
    few events, each with its own line), and one per :meth:`event`. The share done never
    goes back when a new estimate of the total grows (a bisection that finds its bracket):
    it waits until the work catches up. The time left is the elapsed time scaled by the
    work left; when the command first `compiling` the kernels, the pace is taken from the
    first update on (the compilation is not work that will come again), and the time left
    says "compiling" until the pace is known.
    """

    def __init__(self, label: str, total: float, *, unit: str = "",
                 enabled: bool = True, stream: IO[str] | None = None,
                 tty: bool | None = None, tenths: bool = True,
                 compiling: bool = False) -> None:
        self.label, self.total, self.unit, self.tenths = label, float(total), unit, tenths
        self.stream = stream or sys.stderr
        self.enabled = enabled
        self.tty = self.stream.isatty() if tty is None else tty
        self.start = time.monotonic()
        self.done = 0.0
        self.share = 0.0  # of the whole, never decreasing
        self.base = 0.0  # work done before this command (a resumed sweep): not in the pace
        self.compiling = compiling
        self.paced: tuple[float, float] | None = None  # (elapsed, done) the pace starts at
        self.last_tenth = 0  # a line per tenth done: the first at 10 %
        self.bar: Any = None
        if enabled and self.tty:
            from tqdm import tqdm

            self.bar = tqdm(total=BAR_STEPS, desc=label, file=self.stream,
                            dynamic_ncols=True, mininterval=0.2, leave=True,
                            bar_format="{desc}: {percentage:3.0f}%|{bar}| "
                                       "[{elapsed}<{remaining}]{postfix}")

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def remaining(self) -> float | None:
        """Seconds left at the pace so far (None before any work is done, or while the
        kernels compile: before the second update of a compiling command)."""
        if self.total <= 0:
            return None
        t0, d0 = (0.0, self.base) if not self.compiling else (self.paced or (0.0, self.done))
        if self.done <= d0:
            return None
        return (self.elapsed() - t0) * max(self.total - self.done, 0.0) / (self.done - d0)

    def update(self, done: float, note: str = "", total: float | None = None,
               base: float | None = None) -> None:
        """`done` so far (absolute), an optional note, a new estimate of the `total`, the
        work that was `base` done before this command started."""
        if total is not None:
            self.total = float(total)
        if base is not None:
            self.base = float(base)
        done = float(done)
        if self.total > 0 and done >= self.total * (1.0 - DONE_EPS):
            done = self.total
        self.done = min(done, self.total) if self.total > 0 else done
        if self.compiling and self.paced is None:
            self.paced = (self.elapsed(), self.done)
        if self.total > 0:
            self.share = max(self.share, self.done / self.total)
        if not self.enabled:
            return
        if self.bar is not None:
            if base is not None and self.total > 0 and self.bar.n == 0:
                self.bar.initial = self.bar.n = round(BAR_STEPS * self.base / self.total)
            self.bar.set_postfix_str(note, refresh=False)
            self.bar.update(round(BAR_STEPS * self.share) - self.bar.n)
            return
        tenth = int(10 * self.share + DONE_EPS)
        if self.tenths and tenth > self.last_tenth:
            self.last_tenth = tenth
            self._line(note)

    def event(self, text: str) -> None:
        """A line that stays (a trial and its verdict), with the progress so far."""
        if not self.enabled:
            return
        if self.bar is not None:
            self.bar.write(text, file=self.stream)
            return
        self._line(text)

    def _line(self, note: str) -> None:
        left = self.remaining()
        parts = [f"{self.label}: {100.0 * self.share:3.0f} %", f"elapsed {clock(self.elapsed())}",
                 "left ? (compiling)" if left is None and self.compiling
                 else f"left {clock(left)}"]
        print(" · ".join(parts + ([note] if note else [])), file=self.stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
            self.bar = None


def bisection_total(trials: Sequence[tuple[float, bool]], tolerance: float, max_runs: int,
                    relative_to: str = "lo") -> int:
    """How many trials a bisection will take in all, estimated from the trials so far
    (`(value, failed)`): once a failing and a holding value bracket the answer, the halvings
    left until the bracket is narrower than `tolerance` relative to its lower (`lo`) or
    upper (`hi`) end; before that, one more trial to find the bracket. At most `max_runs`."""
    held = [v for v, failed in trials if not failed]
    fail = [v for v, failed in trials if failed]
    n = len(trials)
    if not held or not fail:
        return min(max_runs, n + 1 + (n == 0))
    lo, hi = max(held), min(fail)
    ref = lo if relative_to == "lo" else hi
    if ref <= 0 or hi <= lo:
        return min(max_runs, n)
    halvings = max(0, math.ceil(math.log2((hi - lo) / (tolerance * ref))))
    return min(max_runs, n + halvings)
