"""Issue 40: the service behind a proxy and under hostile input. Forwarded headers count
only from the proxies the operator names; no body gets a 500; replies stay bounded by the
requests; the guard against the open network lives in the app factory."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.api.addresses import ForwardedError, derive_client, parse_networks
from service.jobs.store import JobStore
from tests.service_helpers import Server, cube_scene, free_port, make_client, wait_until

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


# ----------------------------------------------------------------------- no 500 on any body


def _post_text(c: Any, text: str) -> Any:
    return c.post("/jobs", content=text.encode(), headers={"Content-Type": "application/json"})


@pytest.mark.parametrize(("where", "loc"), [
    ("name", "name"), ("description", "description"), ("key", "materials['r\\ud800']"),
    ("block", "blocks[0] ('c\\ud800').name"), ("unknown", "['x\\udc00y']")])
def test_a_lone_surrogate_is_422_naming_the_field(tmp_path: Path, where: str,
                                                  loc: str) -> None:
    """`"cu\\ud800be"` is valid JSON but no text: hashing the request raised
    UnicodeEncodeError, a 500 (without the security headers)."""
    text = json.dumps(cube_scene())
    text = {"name": text.replace('"name": "cube"', '"name": "cu\\ud800be"', 1),
            "description": text.replace("{", '{"description": "a\\ud800", ', 1),
            "key": text.replace("{", '{"materials": {"r\\ud800": {}}, ', 1),
            "block": text.replace('"name": "cube", "vertices"', '"name": "c\\ud800", '
                                  '"vertices"', 1),
            "unknown": text.replace("{", '{"x\\udc00y": 1, ', 1)}[where]
    with make_client(tmp_path / "data") as c:
        r = _post_text(c, text)
        assert r.status_code == 422 and r.headers["content-type"] == PROBLEM, r.text
        assert [e["loc"] for e in r.json()["errors"]] == [loc], r.json()
        assert "lone surrogate" in r.json()["errors"][0]["msg"]
        assert c.get("/jobs").json()["numberMatched"] == 0


def test_the_cli_names_a_lone_surrogate(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    from service.cli.main import main

    path = tmp_path / "scene.json"
    path.write_text(json.dumps(cube_scene()).replace('"cube"', '"cu\\ud800be"', 1))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("name: must be valid Unicode text"), err


def test_every_response_has_the_security_headers_a_500_too(tmp_path: Path) -> None:
    """The error boundary's 500 was sent outside the middleware that adds the headers."""
    from service.api.app import create_app
    from service.settings import Settings
    from tests.service_helpers import TestClient

    app = create_app(Settings(data_dir=tmp_path / "data"), listen="127.0.0.1")

    def broken() -> None:
        raise RuntimeError("a bug")

    app.add_api_route("/broken", broken)
    with TestClient(app, raise_server_exceptions=False) as c:
        r = c.get("/broken")
        assert r.status_code == 500 and r.headers["content-type"] == PROBLEM
        assert r.headers["x-content-type-options"] == "nosniff"
        assert r.headers["x-frame-options"] == "DENY"
        assert r.headers["content-security-policy"].startswith("default-src 'none'")


# ----------------------------------------------------------------------- bounded replies


def test_a_ten_million_character_name_gets_a_small_reply(tmp_path: Path) -> None:
    """The block's name was copied into every error's field path: 20 MB from a 10 MB
    request."""
    scene = cube_scene()
    scene["blocks"][0]["name"] = "x" * 10_000_000
    with make_client(tmp_path / "data", max_body_bytes=20_000_000) as c:
        r = c.post("/jobs", json=scene)
        assert r.status_code == 422 and len(r.content) < 10_000, len(r.content)
        errors = r.json()["errors"]
        assert errors[0]["loc"].startswith("blocks[0] ('xxxx") and len(errors[0]["loc"]) < 130


def test_many_bad_vertices_under_a_long_name_get_a_bounded_reply(tmp_path: Path) -> None:
    """A 1 MB request with 40 bad vertices got a 124 MB 422 after 7.6 s: every error's path
    held the 1 MB name, and every error was listed."""
    scene = cube_scene()
    block = scene["blocks"][0]
    block["name"] = "n" * 1_000_000
    block["vertices"] = block["vertices"] * 5 + [["x", "y", "z"]] * 40
    with make_client(tmp_path / "data") as c:
        t0 = time.monotonic()
        r = c.post("/jobs", json=scene)
        took = time.monotonic() - t0
    assert r.status_code == 422, r.text[:300]
    doc = r.json()
    assert len(r.content) < 60_000, len(r.content)
    assert len(doc["errors"]) == 50 and doc["more_errors"] == 1 + 3 * 40 - 50, (
        len(doc["errors"]), doc.get("more_errors"))
    assert "more" in doc["detail"] and took < 5, took


def test_the_cli_lists_problems_bounded(tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    from service.cli.main import main

    scene = cube_scene()
    scene["blocks"][0]["name"] = "n" * 1_000_000
    scene["blocks"][0]["vertices"] += [["x", "y", "z"]] * 40
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(scene))
    assert main(["validate", str(path)]) == 2
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 51 and lines[-1].startswith("… and "), lines[-1]
    assert max(len(line) for line in lines) < 1000


def test_a_nul_in_the_description_is_refused_and_never_shown_raw(tmp_path: Path) -> None:
    """A NUL in `description` was stored and shown raw in /report."""
    from tests.service_helpers import synthetic_job

    scene = dict(cube_scene(), description="line one\nline\ttwo")
    with make_client(tmp_path / "data") as c:
        assert c.post("/jobs", json=scene).status_code == 201
        r = c.post("/jobs", json=dict(scene, description="a\x00b"))
        assert r.status_code == 422 and r.json()["errors"][0]["loc"] == "description"
    # a job stored before: its page shows a replacement character, not the NUL
    data = tmp_path / "old"
    job_id, _ = synthetic_job(data, n_blocks=2, n_steps=2)
    store = JobStore(data / "jobs.sqlite")
    with store.connect() as db:  # the row as an older service stored it
        db.execute("UPDATE jobs SET scene = ? WHERE id = ?",
                   (json.dumps({"name": "old", "description": "a\x00b"}), job_id))
    with make_client(data) as c:
        for page in (f"/jobs/{job_id}/report", "/?f=html"):
            r = c.get(page)
            assert r.status_code == 200 and "\x00" not in r.text, page


# ----------------------------------------------------------------------- the factory's guard


def test_the_app_factory_refuses_the_network_without_keys(tmp_path: Path) -> None:
    """`uvicorn --factory service.api.app:create_app --host 0.0.0.0` served the network
    without keys: the guard lived in `polydda serve` only. The factory cannot know where
    its launcher listens, so without keys it needs the override; with either it serves."""
    proc = _uvicorn_factory(tmp_path, "0.0.0.0", free_port())
    try:
        assert proc.wait(60) != 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    log = (tmp_path / "uvicorn.log").read_text()
    assert "refusing to serve" in log and "POLYDDA_API_KEYS" in log, log[-2000:]
    for env in ({"POLYDDA_API_KEYS": "k"}, {"POLYDDA_ALLOW_OPEN_NETWORK": "true"}):
        port = free_port()
        proc = _uvicorn_factory(tmp_path, "127.0.0.1", port, **env)
        try:
            wait_until(lambda port=port: _answers(f"http://127.0.0.1:{port}/health"), 60,
                       f"uvicorn to serve with {env}")
        finally:
            proc.terminate()
            proc.wait(30)


def _answers(url: str) -> bool:
    try:
        return httpx.get(url, timeout=1).status_code == 200
    except httpx.TransportError:
        return False


def test_in_process_the_factory_needs_to_know_where_it_listens(tmp_path: Path) -> None:
    from service.api.app import OpenNetworkRefused, create_app
    from service.settings import Settings

    settings = Settings(data_dir=tmp_path / "data")
    for listen in (None, "0.0.0.0", "192.0.2.1"):
        with pytest.raises(OpenNetworkRefused, match="POLYDDA_ALLOW_OPEN_NETWORK"):
            create_app(settings, listen=listen)
    for listen in ("127.0.0.1", "::1", "localhost"):
        create_app(settings, listen=listen)
    create_app(Settings(data_dir=tmp_path / "data", api_keys=frozenset({"k"})))
    create_app(Settings(data_dir=tmp_path / "data", allow_open_network=True), listen="0.0.0.0")


# ----------------------------------------------------------------------- the minor ones


def test_the_quota_message_counts_jobs_and_checks_apart() -> None:
    """With 16 jobs and another submission being checked, the 429 said "you have 17 jobs
    accepted, running or being checked; the limit is 16" while 16 existed."""
    from service.api.problems import Problem
    from service.api.submission import InFlight

    flight = InFlight()
    with flight.hold("ip:a", 15, 16):
        with pytest.raises(Problem) as caught:
            with flight.hold("ip:a", 16, 16):
                pass
    detail = caught.value.detail
    assert detail.startswith("you have 16 unfinished jobs (accepted or running) and 1 more "
                             "submission being checked; the limit is 16"), detail
    with pytest.raises(Problem) as caught, flight.hold("ip:b", 1, 1):
        pass
    assert caught.value.detail.startswith("you have 1 unfinished job (accepted or running); "
                                          "the limit is 1 at once"), caught.value.detail


def test_an_unknown_result_file_says_what_the_job_has(tmp_path: Path) -> None:
    """It said "(it successful: completed 200 steps)"."""
    from tests.service_helpers import synthetic_job

    job_id, _ = synthetic_job(tmp_path / "data", n_blocks=2, n_steps=2)
    with make_client(tmp_path / "data") as c:
        r = c.get(f"/jobs/{job_id}/results/nothing.csv")
    detail = r.json()["detail"]
    assert r.status_code == 404 and "(it " not in detail, detail
    assert f"job {job_id} has no result 'nothing.csv'; the job is successful " \
           "(synthetic: 2 blocks, 2 steps); its results: result.h5" in detail, detail


@pytest.mark.parametrize("attempts", [2, 1])
def test_a_killed_job_process_is_retried_as_after_a_restart(tmp_path: Path,
                                                            attempts: int) -> None:
    """kill -9 of an embedded job process failed the job at once ("resubmit the job"),
    while a restart of the service re-queues its running job: one policy now, at most
    POLYDDA_MAX_ATTEMPTS runs."""
    from tests.service_helpers import job_row, wait_final

    data = tmp_path / "data"
    with make_client(data, max_attempts=attempts) as c:
        url = c.post("/jobs", json=cube_scene(duration=0.6)).headers["Location"]
        wait_until(lambda: (c.get(url).json()["step"] or 0) > 20, 120, "the job to run")
        os.kill(job_row(data, url.rsplit("/", 1)[1])["worker_pid"], 9)
        job = wait_final(c, url, timeout=180)
    if attempts == 2:
        assert job["status"] == "successful" and job["attempts"] == 2, job
    else:
        assert job["status"] == "failed" and job["error_kind"] == "system", job
        assert "its job process ended unexpectedly (killed by signal SIGKILL), 1 time; " \
               "not retried again" in job["message"], job["message"]


def test_the_threat_model_names_tests_that_exist() -> None:
    """Every test docs/service-security.md's threat model names exists (a renamed test
    would leave the table pointing nowhere)."""
    import ast
    import re

    root = Path(__file__).resolve().parent
    page = (root.parent / "docs" / "service-security.md").read_text()
    table = page.split("## Threat model", 1)[1].split("\n## ", 1)[0]
    named = re.findall(r"`(test_[a-z_]+\.py)(?:::(test_[a-z0-9_]+))?`", table)
    assert len(named) >= 20, named
    for module, test in named:
        tree = ast.parse((root / module).read_text())
        names = {f.name for f in tree.body if isinstance(f, ast.FunctionDef)}
        assert not test or test in names, f"{module}::{test}"
