"""`polydda submit`'s client (service.cli.client): one Idempotency-Key per submission, retries of
429 / 503 and cut connections after Retry-After, bounded."""

from __future__ import annotations

import json
from pathlib import Path

import httpx
import pytest

from service.cli.client import MAX_PAUSE, ServiceError, Unreachable, post_with_retries, submit


def _transport(answers: list[httpx.Response | Exception], seen: list[httpx.Request]
               ) -> httpx.MockTransport:
    def handle(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        answer = answers.pop(0)
        if isinstance(answer, Exception):
            raise answer
        return answer
    return httpx.MockTransport(handle)


def _created() -> httpx.Response:
    return httpx.Response(201, json={"jobID": "j1", "status": "accepted", "progress": 0},
                          headers={"Location": "http://svc/jobs/j1"})


def test_429_and_503_are_retried_after_retry_after_with_one_key() -> None:
    seen: list[httpx.Request] = []
    pauses: list[float] = []
    answers: list[httpx.Response | Exception] = [
        httpx.Response(429, headers={"Retry-After": "5"}, json={"title": "quota"}),
        httpx.Response(503, headers={"Retry-After": "3600"}, json={"title": "queue"}),
        httpx.ReadError("connection reset"),  # cut off: the job may exist; the key tells
        _created()]
    with httpx.Client(base_url="http://svc", transport=_transport(answers, seen)) as c:
        r = post_with_retries(c, "/jobs", b"{}", {}, retries=5, sleep=pauses.append)
    assert r.status_code == 201 and len(seen) == 4
    keys = {req.headers["Idempotency-Key"] for req in seen}
    assert len(keys) == 1 and len(keys.pop()) == 36  # one uuid for every attempt
    assert pauses == [5.0, MAX_PAUSE, 4.0]  # Retry-After, capped; backoff after a cut


def test_retries_are_bounded_and_other_errors_are_not_retried() -> None:
    seen: list[httpx.Request] = []
    answers: list[httpx.Response | Exception] = [
        httpx.Response(429, headers={"Retry-After": "1"}, json={}) for _ in range(3)]
    with httpx.Client(base_url="http://svc", transport=_transport(answers, seen)) as c:
        r = post_with_retries(c, "/jobs", b"{}", {}, retries=2, sleep=lambda s: None)
    assert r.status_code == 429 and len(seen) == 3
    seen.clear()
    answers = [httpx.Response(422, json={"detail": "bad scene"})]
    with httpx.Client(base_url="http://svc", transport=_transport(answers, seen)) as c:
        assert post_with_retries(c, "/jobs", b"{}", {}, retries=5).status_code == 422
    assert len(seen) == 1


def test_submit_raises_problems_and_unreachable(tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    scene = tmp_path / "s.json"
    scene.write_text(json.dumps({"blocks": []}))
    answers: list[httpx.Response | Exception] = [
        httpx.Response(422, json={"detail": "d", "errors": [{"loc": "blocks", "msg": "m"}]})]
    transport = _transport(answers, [])
    real = httpx.Client

    def client(**kw: object) -> httpx.Client:
        return real(transport=transport, **kw)  # type: ignore[arg-type]
    monkeypatch.setattr(httpx, "Client", client)
    with pytest.raises(ServiceError, match="blocks: m"):
        submit("http://svc", scene, wait=False)
    answers.append(httpx.ConnectError("refused"))
    with pytest.raises(Unreachable, match="is `polydda serve` running"):
        submit("http://svc", scene, wait=False)
