"""A behaviour-preserving change keeps every example and validation case to 1e-12: the
cases of `tests/digest_cases.py` run again and compare with `tests/data/step_digests.json`
(recorded before the change; re-record with `python -m tests.digest_cases` only for a change
meant to change the physics, and say so in its commit). The chaotic cases (rock masses,
piles, slopes: their paths follow round-off) are compared on the platform that recorded
them only."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.digest_cases import CHAOTIC, DIGESTS, NAMES, digest, platform_key

RECORDED = json.loads(DIGESTS.read_text())


def _close(a: object, b: object, where: str) -> None:
    """Assert `a` equals `b` to 1e-12 relative to the larger magnitude of the series, and
    1e-15 absolute (a series of zeros, or of penetrations of 1e-6 m, moves by ulps of the
    positions it is computed from)."""
    if isinstance(a, dict):
        assert set(a) == set(b), where
        for k in a:
            _close(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, str | int) and not isinstance(a, bool) and not isinstance(a, float):
        assert a == b, f"{where}: {a!r} != {b!r}"
    else:
        x, y = np.asarray(a, float), np.asarray(b, float)
        assert x.shape == y.shape, f"{where}: shape {x.shape} != {y.shape}"
        scale = max(float(np.abs(y).max(initial=0.0)), 1e-300)
        err = float(np.abs(x - y).max(initial=0.0))
        assert err <= 1e-12 * scale + 1e-15, f"{where}: differs by {err:.3g} (scale {scale:.3g})"


@pytest.mark.parametrize("name", NAMES)
def test_case_keeps_its_digest(name: str) -> None:
    recorded_on = RECORDED.get("_platform")
    if name in CHAOTIC and recorded_on != platform_key():
        pytest.skip(f"{name} follows round-off; recorded on {recorded_on}, this is "
                    f"{platform_key()} (re-record: python -m tests.digest_cases)")
    _close(digest(name), RECORDED[name], name)
