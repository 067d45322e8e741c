"""Issue 40's acceptance probe: every request of the issue, against real servers (`polydda
serve`, without keys and with keys), each with and without forwarded headers. No answer is
a 5xx, no reply to a request under 1 MB is over 1 MB, and no client reaches another's job.
`python -m pytest -s tests/test_service_probe.py` prints the counts."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import httpx

from tests.service_helpers import Server, cube_scene, wait_final

MB = 1_000_000
#: the headers a client may forge to pass as another: none, and each of them
FORGED = [{}, {"X-Forwarded-For": "127.0.0.2"}, {"X-Forwarded-For": "127.0.0.2, 127.0.0.1"},
          {"X-Real-IP": "127.0.0.2"}, {"Forwarded": "for=127.0.0.2"},
          {"X-Forwarded-For": "198.51.100.7", "X-Forwarded-Proto": "https"}]


class Probe:
    """Sends requests, keeps every (status, request size, reply size)."""

    def __init__(self) -> None:
        self.seen: list[tuple[str, int, int, int]] = []

    def send(self, c: httpx.Client, method: str, path: str, body: bytes | None = None,
             **headers: str) -> httpx.Response:
        if body is not None:
            headers.setdefault("Content-Type", "application/json")
        r = c.request(method, path, content=body, headers=headers)
        self.seen.append((f"{method} {path.split('?')[0][:40]}", r.status_code,
                          len(body or b""), len(r.content)))
        return r

    def counts(self) -> dict[str, Any]:
        return {"requests": len(self.seen),
                "by status": dict(sorted(Counter(s for _, s, _, _ in self.seen).items())),
                "largest reply to a request under 1 MB": max(
                    (out for _, _, size, out in self.seen if size < MB), default=0),
                "largest request": max(size for _, _, size, _ in self.seen)}


def _scene_text(scene: dict[str, Any]) -> bytes:
    return json.dumps(scene).encode()


def _bodies() -> dict[str, bytes]:
    """The issue's hostile bodies."""
    base = json.dumps(cube_scene(duration=0.01))
    long_name = cube_scene()
    long_name["blocks"][0]["name"] = "x" * 10_000_000
    bad_vertices = cube_scene()
    block = bad_vertices["blocks"][0]
    block["name"] = "n" * 1_000_000
    block["vertices"] = block["vertices"] + [["x", "y", "z"]] * 40
    out = {"surrogate name": base.replace('"name": "cube"', '"name": "cu\\ud800be"', 1),
           "surrogate description": base.replace("{", '{"description": "a\\ud800b", ', 1),
           "surrogate key": base.replace("{", '{"materials": {"r\\ud800": {}}, ', 1),
           "nul description": base.replace("{", '{"description": "a\\u0000b", ', 1)}
    bodies = {k: v.encode() for k, v in out.items()}
    bodies["10,000,000-character name"] = _scene_text(long_name)
    bodies["1 MB, 40 bad vertices"] = _scene_text(bad_vertices)
    for name, change in {
            "density 1e200": {"materials": {"rock": {"density": 1e200}}},
            "density 1e308": {"materials": {"rock": {"density": 1e308}}},
            "density 1e-300": {"materials": {"rock": {"density": 1e-300}}},
            "gravity 1e300": {"gravity": [0, 0, -1e300]}}.items():
        bodies[name] = _scene_text(cube_scene() | change)
    penalty = cube_scene()
    penalty["analysis"]["penalty"] = 1e300
    bodies["penalty 1e300"] = _scene_text(penalty)
    return bodies


def _no_key_server(tmp_path: Path, probe: Probe) -> None:
    """Without keys: the hostile bodies, then 127.0.0.1 with every forged header against
    127.0.0.2's job."""
    with Server(tmp_path / "open") as srv, \
            httpx.Client(base_url=srv.url, timeout=120) as here, \
            httpx.Client(base_url=srv.url, timeout=120, transport=httpx.HTTPTransport(
                local_address="127.0.0.2")) as owner:
        for name, body in _bodies().items():
            r = probe.send(here, "POST", "/jobs", body)
            assert r.status_code == 422, (name, r.status_code, r.text[:300])
        url = probe.send(owner, "POST", "/jobs",
                         _scene_text(cube_scene(duration=0.01))).headers["Location"]
        path = httpx.URL(url).path
        assert wait_final(owner, path, timeout=120)["status"] == "successful"
        for headers in FORGED:
            r = probe.send(here, "GET", "/jobs", **headers)
            assert r.status_code in (200, 400) and path not in r.text, headers
            for sub in ("", "/results", "/results/result.h5", "/results/nothing.csv",
                        "/report", "/viewer", "/results/frames"):
                r = probe.send(here, "GET", path + sub, **headers)
                assert r.status_code in (400, 404), (headers, sub, r.status_code)
            r = probe.send(here, "DELETE", path, **headers)
            assert r.status_code in (400, 404), (headers, r.status_code)
        r = probe.send(owner, "GET", path + "/results/nothing.csv")
        assert r.status_code == 404 and "(it " not in r.json()["detail"]
        assert probe.send(owner, "GET", path).status_code == 200  # still there


def _keyed_server(tmp_path: Path, probe: Probe) -> None:
    """With keys: another key never sees a job, forged headers or not; wrong keys are
    throttled per address whatever X-Forwarded-For says."""
    with Server(tmp_path / "keyed", POLYDDA_API_KEYS="alpha,beta") as srv, \
            httpx.Client(base_url=srv.url, timeout=120) as c:
        url = probe.send(c, "POST", "/jobs", _scene_text(cube_scene(duration=0.01)),
                         **{"X-API-Key": "alpha"}).headers["Location"]
        path = httpx.URL(url).path
        for headers in FORGED:
            for sub in ("", "/results", "/report"):
                r = probe.send(c, "GET", path + sub, **{"X-API-Key": "beta", **headers})
                assert r.status_code in (400, 404), (headers, sub, r.status_code)
            r = probe.send(c, "DELETE", path, **{"X-API-Key": "beta", **headers})
            assert r.status_code in (400, 404), headers
        codes = [probe.send(c, "GET", "/jobs", **{"X-API-Key": f"wrong{k}",
                                                  "X-Forwarded-For": f"198.51.100.{k}"})
                 .status_code for k in range(30)]
        assert codes == [401] * 10 + [429] * 20, codes
        for headers in FORGED:
            r = probe.send(c, "GET", path, **{"X-API-Key": "alpha", **headers})
            assert r.status_code in (400, 429), (headers, r.status_code)


def test_the_issues_probe(tmp_path: Path) -> None:
    probe = Probe()
    _no_key_server(tmp_path, probe)
    _keyed_server(tmp_path, probe)
    counts = probe.counts()
    print("\nprobe:", json.dumps(counts))
    assert not [s for s in counts["by status"] if s >= 500], counts
    assert counts["largest reply to a request under 1 MB"] < MB, counts
    big = [(what, out) for what, _, size, out in probe.seen if out > max(MB, 4 * size)]
    assert not big, big
