"""Job results in an S3-compatible object store (service.jobs.objectstore) against a real
S3 server started here (moto's server mode), and two RQ workers with separate data
directories whose jobs' results the API serves from the store."""

from __future__ import annotations

import hashlib
import os
import shutil
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.jobs.objectstore import PART, ResultStore
from tests.service_helpers import (
    RedisServer,
    Server,
    cube_scene,
    free_port,
    wait_final,
    wait_until,
    worker_command,
)

moto_server = pytest.importorskip("moto.server")
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "polydda-test", "AWS_SECRET_ACCESS_KEY": "polydda-test",
               "AWS_DEFAULT_REGION": "us-east-1"}
BUCKET = "results"


@pytest.fixture
def s3(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A real S3 endpoint on loopback (moto's server) with an empty bucket; its URL."""
    for k, v in CREDENTIALS.items():
        monkeypatch.setenv(k, v)
    port = free_port()
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    url = f"http://127.0.0.1:{port}"
    try:
        import boto3

        boto3.client("s3", endpoint_url=url).create_bucket(Bucket=BUCKET)
        yield url
    finally:
        server.stop()


def test_store_uploads_in_parts_and_streams_ranges(s3: str, tmp_path: Path) -> None:
    """A 20 MiB file goes up in 8 MiB parts (multipart: the stored object's ETag says how
    many) and comes back whole and by byte range; the manifest lists what is stored."""
    job = tmp_path / "job"
    job.mkdir()
    big = os.urandom(20 * 1024 * 1024)
    (job / "result.h5").write_bytes(big)
    (job / "summary.json").write_text('{"steps": 3}')
    (job / ".summary.json.tmp").write_text("half")  # a temporary: never uploaded
    store = ResultStore(BUCKET, "p/", s3)
    files = store.upload_job("j1", job)
    assert files == {"result.h5": len(big), "summary.json": 12}
    head = store.client.head_object(Bucket=BUCKET, Key="p/jobs/j1/result.h5")
    assert head["ETag"].strip('"').endswith(f"-{-(-len(big) // PART)}")  # 3 parts
    assert b"".join(store.stream("j1", "result.h5")) == big
    assert b"".join(store.stream("j1", "result.h5", 5, 1_000_004)) == big[5:1_000_005]
    assert store.manifest("j1") == files and store.manifest("nope") is None
    copy = tmp_path / "copy"
    assert store.fetch_job("j1", copy) and (copy / "result.h5").read_bytes() == big
    store.delete_job("j1")
    assert store.manifest("j1") is None


def test_two_workers_with_their_own_data_dirs_and_the_api_serves_from_s3(
        s3: str, tmp_path: Path) -> None:
    """The API and two `polydda worker`s share Redis and the bucket, not a file system:
    every job's results (document, result.h5 whole and by Range, report) are served, and
    the API's data directory had none of their files before it was asked."""
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed (apt-get install -y redis-server)")
    s3_env = {"POLYDDA_S3_BUCKET": BUCKET, "POLYDDA_S3_ENDPOINT_URL": s3, **CREDENTIALS}
    with RedisServer(tmp_path) as redis:
        workers = []
        for k in range(2):
            env = {**os.environ, **s3_env, "POLYDDA_DATA_DIR": str(tmp_path / f"w{k}"),
                   "POLYDDA_REDIS_URL": redis.url}
            log = open(tmp_path / f"w{k}.log", "ab")  # noqa: SIM115 (closed with the worker)
            workers.append((subprocess_popen(worker_command("--name", f"s3w{k}-{os.getpid()}"),
                                             env, tmp_path, log), log))
        try:
            api = tmp_path / "api"
            srv = Server(api, POLYDDA_BACKEND="rq", POLYDDA_REDIS_URL=redis.url, **s3_env)
            srv.start(timeout=120)  # (a loaded machine starts it slowly)
            try:
                with httpx.Client(base_url=srv.url, timeout=60) as c:
                    wait_until(lambda: c.get("/health").json()["workers"] == 2, 120,
                               "both workers to be live")
                    urls = [c.post("/jobs", json=cube_scene(duration=0.02 + 0.01 * k))
                            .headers["Location"] for k in range(4)]
                    docs = [wait_final(c, u, 120) for u in urls]
                    assert all(d["status"] == "successful" for d in docs), docs
                    ran = {k for k in range(2) if any((tmp_path / f"w{k}" / "jobs").glob("*"))}
                    assert ran == {0, 1}, "both workers ran jobs"
                    job_ids = [u.rsplit("/", 1)[1] for u in urls]
                    assert not any((api / "jobs" / j).exists() for j in job_ids)
                    store = ResultStore(BUCKET, "polydda/", s3)
                    for u, j, k in zip(urls, job_ids, range(4), strict=True):
                        whole = c.get(u + "/results/result.h5")
                        assert whole.status_code == 200
                        stored = b"".join(store.stream(j, "result.h5"))
                        assert hashlib.sha256(whole.content).digest() == \
                            hashlib.sha256(stored).digest()
                        part = c.get(u + "/results/result.h5", headers={"Range": "bytes=8-1031"})
                        assert part.status_code == 206 and part.content == stored[8:1032]
                        assert part.headers["content-range"] == f"bytes 8-1031/{len(stored)}"
                        bad = c.get(u + "/results/result.h5",
                                    headers={"Range": f"bytes={len(stored)}-"})
                        assert bad.status_code == 416
                        res = c.get(u + "/results").json()
                        assert res["summary"]["steps"] == 20 + 10 * k
                    assert c.get(urls[0] + "/report").status_code == 200
                    assert c.delete(urls[0]).status_code == 200
                    assert store.manifest(job_ids[0]) is None  # dismissed: gone from the store
            finally:
                srv.stop()
        finally:
            for w, log in workers:
                w.terminate()
                w.wait(20)
                log.close()


def subprocess_popen(cmd: list[str], env: dict[str, str], cwd: Path, log: object) -> object:
    import subprocess

    return subprocess.Popen(cmd, env=env, cwd=cwd, stdout=log, stderr=subprocess.STDOUT)
