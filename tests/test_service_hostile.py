"""Issue 40: the service behind a proxy and under hostile input. Forwarded headers count
only from the proxies the operator names; no body gets a 500; replies stay bounded by the
requests; the guard against the open network lives in the app factory."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from service.api.addresses import ForwardedError, derive_client, parse_networks
from tests.service_helpers import Server, cube_scene, free_port, wait_until

PROBLEM = "application/problem+json"
LOCAL2 = httpx.HTTPTransport(local_address="127.0.0.2")


def _xff(*values: str) -> list[tuple[bytes, bytes]]:
    return [(b"x-forwarded-for", v.encode()) for v in values]


# ----------------------------------------------------------------------- forwarded headers


@pytest.mark.parametrize(("peer", "headers", "trusted", "wanted"), [
    # no trusted proxy: the headers are ignored
    ("127.0.0.1", _xff("198.51.100.7"), "", "127.0.0.1"),
    ("203.0.113.5", _xff("10.0.0.1, 198.51.100.7"), "", "203.0.113.5"),
    # a trusted proxy: the right-most entry it did not add itself... and no further
    ("10.0.0.2", _xff("198.51.100.7"), "10.0.0.0/8", "198.51.100.7"),
    ("10.0.0.2", _xff("1.1.1.1, 198.51.100.7, 10.0.0.9"), "10.0.0.0/8", "198.51.100.7"),
    ("10.0.0.2", _xff("1.1.1.1", "198.51.100.7:4711"), "10.0.0.0/8", "198.51.100.7"),
    ("::1", _xff("[2001:db8::7]:443"), "::1", "2001:db8::7"),
    ("10.0.0.2", [], "10.0.0.0/8", "10.0.0.2"),
    # a peer that is not trusted, beside a trusted network
    ("192.168.1.9", _xff("198.51.100.7"), "10.0.0.0/8", "192.168.1.9"),
])
def test_the_client_address_comes_from_trusted_proxies_only(
        peer: str, headers: list[tuple[bytes, bytes]], trusted: str, wanted: str) -> None:
    nets = parse_networks([t for t in trusted.split(",") if t])
    assert derive_client(peer, headers, "http", nets)[0] == wanted


def test_a_server_that_took_the_address_from_the_header_is_not_believed() -> None:
    """Under a launcher that rewrote the peer from X-Forwarded-For (uvicorn's default from
    127.0.0.1), the peer the app sees is one of the header's entries: refused unless a
    trusted proxy sent it."""
    with pytest.raises(ForwardedError, match="--no-proxy-headers"):
        derive_client("127.0.0.2", _xff("127.0.0.2"), "http", ())
    with pytest.raises(ForwardedError, match="no IP address"):
        derive_client("10.0.0.2", _xff("somewhere"), "http", parse_networks(["10.0.0.2"]))
    scheme = [(b"x-forwarded-proto", b"https")]
    assert derive_client("10.0.0.2", scheme, "http", parse_networks(["10.0.0.2"]))[1] == "https"
    assert derive_client("10.0.0.3", scheme, "http", parse_networks(["10.0.0.2"]))[1] == "http"


def test_a_forwarded_header_does_not_turn_one_local_client_into_another(
        tmp_path: Path) -> None:
    """Without keys, 127.0.0.1 sending `X-Forwarded-For: 127.0.0.2` read, listed,
    downloaded and deleted 127.0.0.2's job (uvicorn believed the header from 127.0.0.1)."""
    with Server(tmp_path / "data") as srv:
        owner = httpx.Client(base_url=srv.url, timeout=30, transport=LOCAL2)
        other = httpx.Client(base_url=srv.url, timeout=30,
                             headers={"X-Forwarded-For": "127.0.0.2"})
        with owner, other:
            url = owner.post("/jobs", json=cube_scene(duration=0.01)).headers["Location"]
            path = httpx.URL(url).path
            wait_until(lambda: owner.get(path).json()["status"] == "successful", 60,
                       "the job to end")
            assert other.get("/jobs").json()["numberMatched"] == 0
            for method, sub in (("GET", ""), ("GET", "/results/result.h5"), ("DELETE", "")):
                r = other.request(method, path + sub)
                assert r.status_code == 404, (method, sub, r.status_code)
            assert owner.get(path).status_code == 200
        log = srv.log.read_text(errors="replace")
        assert '127.0.0.2:0 - "GET' not in log  # the access log names the real peer


def test_a_forwarded_header_does_not_escape_the_wrong_key_throttle(tmp_path: Path) -> None:
    """After 10 wrong keys even the right key gets 429; a forged X-Forwarded-For gave 200,
    and wrong keys each with another header value were never throttled."""
    with Server(tmp_path / "data", POLYDDA_API_KEYS="right") as srv, \
            httpx.Client(base_url=srv.url, timeout=30) as c:
        codes = [c.get("/jobs", headers={"X-API-Key": f"wrong{k}",
                                         "X-Forwarded-For": f"198.51.100.{k}"}).status_code
                 for k in range(30)]
        assert codes == [401] * 10 + [429] * 20, codes
        r = c.get("/jobs", headers={"X-API-Key": "right", "X-Forwarded-For": "198.51.100.7"})
        assert r.status_code == 429


def test_a_trusted_proxy_names_its_clients(tmp_path: Path) -> None:
    """With POLYDDA_TRUSTED_PROXIES=127.0.0.1 (a proxy on the host), each client behind it
    is the address it forwards, for ownership and the log; a client connecting past the
    proxy (127.0.0.2) cannot claim another's address."""
    with Server(tmp_path / "data", POLYDDA_TRUSTED_PROXIES="127.0.0.1") as srv:
        a = httpx.Client(base_url=srv.url, timeout=30,
                         headers={"X-Forwarded-For": "203.0.113.10"})
        b = httpx.Client(base_url=srv.url, timeout=30,
                         headers={"X-Forwarded-For": "203.0.113.11"})
        past = httpx.Client(base_url=srv.url, timeout=30, transport=LOCAL2,
                            headers={"X-Forwarded-For": "203.0.113.10"})
        with a, b, past:
            url = a.post("/jobs", json=cube_scene(duration=0.01)).headers["Location"]
            path = httpx.URL(url).path
            assert a.get(path).status_code == 200
            assert b.get(path).status_code == 404
            assert past.get(path).status_code == 404
            assert past.get("/jobs").json()["numberMatched"] == 0
        assert '203.0.113.10:0 - "POST /jobs' in srv.log.read_text(errors="replace")


def _uvicorn_factory(tmp_path: Path, host: str, port: int, **env: str) -> subprocess.Popen:
    """`uvicorn --factory service.api.app:create_app` with uvicorn's defaults (it believes
    X-Forwarded-For from 127.0.0.1), as the app's docstring advertises it."""
    base = {k: v for k, v in os.environ.items() if not k.startswith("POLYDDA_")}
    root = str(Path(__file__).resolve().parents[1])
    with open(tmp_path / "uvicorn.log", "ab") as log:
        return subprocess.Popen(
            [sys.executable, "-m", "uvicorn", "--factory", "service.api.app:create_app",
             "--host", host, "--port", str(port)],
            env={**base, "PYTHONPATH": root, "POLYDDA_DATA_DIR": str(tmp_path / "data"),
                 **env}, cwd=tmp_path, stdout=log, stderr=subprocess.STDOUT)


def test_under_a_launcher_that_believes_the_header_forging_is_refused(tmp_path: Path) -> None:
    """uvicorn --factory keeps its trust of X-Forwarded-For from 127.0.0.1: the app sees
    the forged address as the peer, recognizes it among the header's entries and refuses
    the request instead of serving another client's job."""
    port = free_port()
    proc = _uvicorn_factory(tmp_path, "127.0.0.1", port, POLYDDA_ALLOW_OPEN_NETWORK="true")
    url = f"http://127.0.0.1:{port}"
    try:
        def up() -> bool:
            assert proc.poll() is None, (tmp_path / "uvicorn.log").read_text()
            try:
                return httpx.get(url + "/health", timeout=1).status_code == 200
            except httpx.TransportError:
                return False
        wait_until(up, 60, "uvicorn to start")
        with httpx.Client(base_url=url, timeout=30, transport=LOCAL2) as owner:
            loc = owner.post("/jobs", json=cube_scene(duration=0.01)).headers["Location"]
        path = httpx.URL(loc).path
        r = httpx.get(url + path, headers={"X-Forwarded-For": "127.0.0.2"}, timeout=30)
        assert r.status_code == 400 and r.headers["content-type"] == PROBLEM, r.text
        assert "--no-proxy-headers" in r.json()["detail"]
        assert r.headers["x-content-type-options"] == "nosniff"
        assert httpx.get(url + path, timeout=30).status_code == 404
    finally:
        proc.terminate()
        proc.wait(30)
