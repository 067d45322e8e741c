"""Property-based API testing from the OpenAPI spec (schemathesis) against a real server on
its default settings, with every check (`--checks all`). The stateless run draws the
`job_id` of the job operations from jobs made for it (a simulation and a limit-equilibrium
job that have ended; DELETE from jobs of its own), so those operations answer with real
results, not only 404s.

Every generated request must get a documented answer: no 5xx, only documented status codes
(ST103), responses that match the schema (problem+json for errors), invalid data rejected,
valid data accepted (ST202). Two tunings, as schemathesis documents for rules a schema cannot
express: a scene can match the Scene schema and still not be a block system (open or
overlapping blocks, unknown names; the submissions' OpenAPI description lists these and
the service's limits), so a submission may refuse a schema-valid scene with 422 - and then
only as an `invalid-scene` problem naming the fields; and which steps a result recorded
depends on the run, so the contacts of a step (≥ 0, as the schema says) that was not
recorded, and frames from a step beyond those recorded, are refused with 422 - and then
only as a `Step(s) not recorded` problem naming `query.step` or `query.start` (all checked
here too).
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, settings  # noqa: E402
from hypothesis.errors import FlakyStrategyDefinition  # noqa: E402

from tests.service_helpers import Server  # noqa: E402

#: schemathesis's configuration: every check; submissions may refuse a schema-valid scene,
#: and the contacts and frames steps that were not recorded, with 422 (see the module)
CONFIG = """
[[operations]]
include-operation-id = ["createJob", "executeProcess", "builderValidate", "builderPreview",
                        "builderStereonet", "builderTerrain"]
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "409", "422",
                                                     "429", "5xx"]

[[operations]]
include-operation-id = ["getContacts", "getFrames"]
checks.positive_data_acceptance.expected-statuses = ["2xx", "401", "404", "409", "422",
                                                     "429", "5xx"]
"""
SUBMISSIONS = ("createJob", "executeProcess")
#: the scene builder's routes: a schema-valid scene, measurement text or file may still be
#: refused with 422, as an invalid-scene problem naming what is wrong
BUILDER = ("builderValidate", "builderPreview", "builderStereonet", "builderTerrain")


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    data = tmp_path_factory.mktemp("fuzz") / "data"
    with Server(data, POLYDDA_MAX_WORKERS="1") as srv:  # the default settings
        yield srv


def _config(jobs: list[str] | None = None, doomed: list[str] | None = None) -> Any:
    """The configuration; with `jobs`, the job operations' `job_id` is drawn from them
    (DELETE's from `doomed`: what it removes is gone for the other operations)."""
    from schemathesis.config import SchemathesisConfig

    text = CONFIG
    if jobs:
        text = _with_ids(text, jobs, doomed or jobs)
    return SchemathesisConfig.from_str(text)


#: the result files of the jobs the stateless run uses (service.jobs.processes)
FILES = '"result.h5", "summary.json", "le.json"'


def _with_ids(text: str, jobs: list[str], doomed: list[str]) -> str:
    quoted = ", ".join(f'"{j}"' for j in jobs)
    gone = ", ".join(f'"{j}"' for j in doomed)
    # project settings go before the [[operations]] tables (TOML: a key after a table
    # header belongs to that table)
    return (f'parameters = {{ "path.job_id" = {{ dictionary = "jobs", probability = 0.9 }} }}\n'
            f"dictionaries = {{ jobs = {{ values = [{quoted}] }}, "
            f"doomed = {{ values = [{gone}] }}, files = {{ values = [{FILES}] }} }}\n"
            + text + '''
[[operations]]
include-operation-id = ["dismissJob"]
parameters = { "path.job_id" = { dictionary = "doomed", probability = 0.9 } }

[[operations]]
include-operation-id = ["getResultFile"]
[operations.parameters]
"path.job_id" = { dictionary = "jobs", probability = 0.9 }
"path.name" = { dictionary = "files", probability = 0.8 }
''')


def _ended_jobs(url: str) -> tuple[list[str], list[str]]:
    """A simulation and a limit-equilibrium job that have ended (the ids the stateless run
    uses), and one more for DELETE to remove."""
    import httpx

    from tests.service_helpers import ROOT, cube_scene, wait_final

    planar = json.loads((ROOT / "examples" / "planar_tendon.json").read_text())
    with httpx.Client(base_url=url, timeout=60) as c:
        urls = [c.post("/jobs", json=cube_scene(duration=0.01)).headers["Location"],
                c.post("/processes/limit-equilibrium/execution", json=planar)
                .headers["Location"]]
        urls.append(c.post("/jobs", json=cube_scene(duration=0.01)).headers["Location"])
        for job_url in urls:
            assert wait_final(c, job_url, timeout=180)["status"] == "successful", job_url
    ids = [u.rsplit("/", 1)[1] for u in urls]
    return ids[:2], ids[2:]


@pytest.fixture(scope="module")
def api_schema(server: Server) -> object:
    jobs, doomed = _ended_jobs(server.url)
    return schemathesis.openapi.from_url(server.url + "/openapi.json",
                                         config=_config(jobs, doomed))


schema = schemathesis.pytest.from_fixture("api_schema")


def _documented_422(case: Any, response: Any) -> None:
    """A 422 for schema-valid data is one the API documents: a submission's names what is
    wrong with the scene (or says its Idempotency-Key came with another body), the
    contacts' and the frames' say the steps were not recorded."""
    op = case.operation.definition.raw.get("operationId")
    meta = getattr(case, "meta", None)
    positive = meta is not None and meta.generation.mode.is_positive
    if op in SUBMISSIONS + BUILDER and positive and response.status_code == 422:
        doc = response.json()
        if doc["type"].endswith("/idempotency-key-reused"):  # a key sent with another body
            return
        assert doc["type"].endswith(("/invalid-scene", "/invalid-request")), doc
        assert doc["errors"] and all(e["msg"] for e in doc["errors"]), doc
    steps = {"getContacts": ("Step not recorded", "query.step"),
             "getFrames": ("Steps not recorded", "query.start")}
    if op in steps and positive and response.status_code == 422:
        doc = response.json()
        title, loc = steps[op]
        assert doc["title"] == title, doc
        assert [e["loc"] for e in doc["errors"]] == [loc], doc


#: (operation, status) of every stateless call
SEEN: list[tuple[str, int]] = []


@schema.parametrize()
@settings(max_examples=25, deadline=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
def test_api_answers_every_generated_request(case: object) -> None:
    response = case.call_and_validate(timeout=30)  # type: ignore[attr-defined]
    _documented_422(case, response)
    SEEN.append((str(case.operation.definition.raw.get("operationId")),  # type: ignore[attr-defined]
                 response.status_code))


def test_the_job_operations_saw_real_jobs() -> None:
    """With job ids drawn from real jobs, the job operations answered 2xx, not only 404."""
    ok = {op for op, code in SEEN if 200 <= code < 300}
    wanted = {"getJob", "getResults", "getContacts", "getFrames", "getResultFile",
              "jobViewer", "jobReport", "jobEvents", "dismissJob"}
    assert wanted <= ok, sorted(wanted - ok)


def test_server_still_healthy(server: Server) -> None:
    import httpx

    assert httpx.get(server.url + "/health", timeout=10).json()["status"] == "ok"
    log = Path(server.log).read_text(errors="replace")
    assert "Traceback" not in log, log[-3000:]


@pytest.fixture(scope="module")
def linked_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    """As `server`, with a quota no sequence reaches (a 429 here or there would make the
    sequences Hypothesis replays behave differently)."""
    data = tmp_path_factory.mktemp("linked") / "data"
    env = {"POLYDDA_CLIENT_QUOTA": "100000", "POLYDDA_MAX_WORKERS": "1"}
    with Server(data, **env) as srv:
        yield srv


def test_api_answers_call_sequences_that_follow_its_links(linked_server: Server) -> None:
    """Stateful: the fuzzer creates jobs and follows the OpenAPI links of the answers
    (status, events, results, plots, contacts, frames, viewer, dismissal) with the real job
    ids, so those operations are fuzzed beyond 404s. Created jobs get a small valid scene
    (a generated one is rarely runnable; the stateless test fuzzes the bodies)."""
    from tests.service_helpers import cube_scene

    seen: list[tuple[str, int, bool]] = []
    base = schemathesis.openapi.from_url(linked_server.url + "/openapi.json",
                                         config=_config()).as_state_machine()

    def op_id(case: Any) -> str:
        return str(case.operation.definition.raw.get("operationId"))

    class Linked(base):  # type: ignore[misc, valid-type]
        def before_call(self, case: Any) -> None:
            if op_id(case) in ("createJob", "executeProcess"):
                case.body = cube_scene(duration=0.01)

        def after_call(self, response: Any, case: Any) -> None:
            unknown = response.status_code == 404 and b"/no-such-job" in response.content
            seen.append((op_id(case), response.status_code, unknown))

        def validate_response(self, response: Any, case: Any, additional_checks: Any = None,
                              **kwargs: Any) -> None:
            try:
                case.validate_response(response, additional_checks=additional_checks,
                                       transport_kwargs=kwargs or None)
                _documented_422(case, response)
            except Exception as exc:
                failures.append(exc)
                raise

    failures: list[Exception] = []
    # a job operation reached with a real id: any answer but 404 no-such-job (which ones
    # answer 2xx depends on whether the job had ended by then)
    job_ops = {"getJob", "jobEvents", "getResults", "listPlots", "getContacts", "getFrames",
               "jobViewer", "dismissJob"}
    # Which links the sequences follow depends on the server's answers, and those on how
    # fast its jobs end (under load, one derandomized round once reached only dismissJob):
    # the derandomized round first, then up to two random rounds until the sequences have
    # reached the job operations. A failed check fails the test in any round.
    for derandomize in (True, False, False):
        replay = "all replays drew alike"
        try:
            Linked.run(settings=settings(max_examples=30, stateful_step_count=6, deadline=None,
                                         derandomize=derandomize, database=None,
                                         suppress_health_check=list(HealthCheck)))
        except FlakyStrategyDefinition:
            # a replay drew differently because the server's state moved on (more jobs in
            # GET /jobs, a job that has ended): schemathesis's own runner treats it so
            # too. Only a failed check fails the test.
            if failures:
                raise failures[0] from None
            replay = "a replay drew differently (the server's state moved on)"
        reached = {op for op, _, unknown in seen if op in job_ops and not unknown}
        ok = {op for op, code, _ in seen if 200 <= code < 300}
        print(f"\nstateful ({'derandomized' if derandomize else 'random'}): {len(seen)} "
              f"calls; job operations reached with real ids: {sorted(reached)}; answered "
              f"2xx: {sorted(ok)}; {replay}")
        if "getJob" in ok and len(reached) >= 4:
            break
    assert "getJob" in ok and len(reached) >= 4, seen
    # and, whatever the sequences were, each linked operation once on an ended job
    import httpx

    from service.api.openapi import JOB_LINKS
    from tests.service_helpers import wait_final

    schema = base.schema
    with httpx.Client(base_url=linked_server.url, timeout=30) as c:
        # the sequences may have left long jobs (a factor of safety of the cube) queued
        # before this one: cancel them
        left = c.get("/jobs", params={"status": ["accepted", "running"], "limit": 1000})
        for job in left.json()["jobs"]:
            c.delete(f"/jobs/{job['jobID']}")
        url = c.post("/jobs", json=cube_scene(duration=0.01)).headers["Location"]
        assert wait_final(c, url, timeout=120)["status"] == "successful"
    job_id = url.rsplit("/", 1)[1]
    for op, _ in sorted(JOB_LINKS.values(), key=lambda v: v[0] == "dismissJob"):
        case = schema.find_operation_by_id(op).Case(path_parameters={"job_id": job_id})
        response = case.call(timeout=30)
        assert response.status_code < 300, (op, response.status_code, response.text[:500])
        case.validate_response(response)
    log = Path(linked_server.log).read_text(errors="replace")
    assert "Traceback" not in log, log[-3000:]
