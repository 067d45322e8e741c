"""Service settings: one pydantic-settings object, read from `POLYDDA_*` environment variables.

Example: `POLYDDA_DATA_DIR=/data POLYDDA_BACKEND=rq POLYDDA_REDIS_URL=redis://redis:6379/0`.
`POLYDDA_API_KEYS`, `POLYDDA_ADMIN_KEYS` and `POLYDDA_CORS_ORIGINS` are comma-separated
lists (empty API keys: no key needed, and every client sees only the jobs of its address;
the app factory then serves loopback only, unless POLYDDA_ALLOW_OPEN_NETWORK=true).
`POLYDDA_TRUSTED_PROXIES` lists the reverse proxies (addresses or networks) whose
X-Forwarded-For and X-Forwarded-Proto are believed; empty (the default): nobody's.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict


class Settings(BaseSettings):
    """Everything the API process, the embedded workers and the RQ workers are configured by."""

    model_config = SettingsConfigDict(env_prefix="POLYDDA_", extra="ignore")

    data_dir: Path = Field(Path("polydda-data"),
                           description="job table (jobs.sqlite) and results (jobs/<id>/)")
    backend: Literal["embedded", "rq"] = Field(
        "embedded", description="embedded: processes of the API host; rq: RQ workers via Redis")
    redis_url: str = "redis://127.0.0.1:6379/0"
    rq_queue: str = "polydda"
    max_workers: int = Field(default_factory=lambda: os.cpu_count() or 1, ge=1,
                             description="embedded backend: jobs running at once")
    max_body_bytes: int = Field(10 * 1024 * 1024, ge=1024, description="largest request body")
    max_vertices: int = Field(50_000, ge=8, description="vertices in all blocks of a scene")
    max_blocks: int = Field(5_000, ge=1,
                            description="blocks of a scene: explicit ones, and those its joints "
                                        "would cut the domain into (estimated before cutting)")
    max_duration: float = Field(3600.0, gt=0, description="largest simulated duration (s)")
    max_steps: int = Field(5_000_000, ge=1, description="largest duration / time_step")
    api_keys: Annotated[frozenset[str], NoDecode] = Field(
        frozenset(), description="accepted X-API-Key values; empty: keys are not checked. A "
                                 "job belongs to the key that created it; other keys get 404")
    admin_keys: Annotated[frozenset[str], NoDecode] = Field(
        frozenset(), description="keys that see, download and dismiss every job (also "
                                 "accepted as API keys); empty: no admin")
    rate_limit: float = Field(0.0, ge=0, description="requests per second per client "
                                                     "(API key or address); 0: no limit")
    rate_burst: int = Field(20, ge=1, description="requests a client may send at once "
                                                  "above its rate")
    cors_origins: Annotated[tuple[str, ...], NoDecode] = Field(
        (), description="origins browsers may call the API from ('*' for any); empty: no "
                        "CORS headers")
    retention: float = Field(30 * 24 * 3600.0, ge=0,
                             description="s a finished job and its files are kept after it "
                                         "ended; 0: forever")
    min_free_bytes: int = Field(1 << 30, ge=0,
                                description="new jobs are refused (507) when the data "
                                            "directory's disk has less free space than this")
    keep_alive: float = Field(
        75.0, gt=0, description="s an idle HTTP connection stays open; longer than any "
                                "Retry-After the API sends, so a client that waits as "
                                "told reuses a live connection")
    rq_heartbeat_ttl: float = Field(
        10.0, gt=0, description="RQ: s a job's heartbeat lives; a job whose worker stopped "
                                "beating is re-queued (or failed after max_attempts) this "
                                "long after its last beat")
    client_quota: int = Field(16, ge=1,
                              description="unfinished (accepted or running) jobs per client")
    worker_threads: int = Field(
        1, ge=1, description="OMP/BLAS and numba threads of a job process (2 lets one job "
                             "detect a large rock mass's contacts on both cores of a "
                             "2-core machine)")
    worker_nice: int = Field(5, ge=0, le=19, description="niceness of job processes")
    progress_interval: float = Field(0.25, gt=0, description="s between progress writes")
    cancel_grace: float = Field(1.0, ge=0,
                                description="s a cancelled job may take before it is killed")
    max_attempts: int = Field(2, ge=1,
                              description="runs of a job whose worker or service was lost "
                                          "while it ran (then it fails, kind system)")
    job_timeout: int = Field(7 * 24 * 3600, ge=1, description="RQ job timeout (s)")
    validation_workers: int = Field(
        1, ge=1, description="processes that check submitted scenes' geometry (cutting, "
                             "closure, overlaps) apart from the API process")
    validation_timeout: float = Field(
        120.0, gt=0, description="s a scene's geometry check may take; a scene that takes "
                                 "longer is refused (422)")
    validation_budget: float = Field(
        120.0, gt=0, description="s of geometry checking per client per minute (a client "
                                 "over it gets 429 until its budget refills)")
    preview_timeout: float = Field(
        30.0, gt=0, description="s the scene builder's preview (cutting the blocks and their "
                                "key-block verdicts) may take; a longer one is refused (422), "
                                "and it is charged to the client's validation budget")
    auth_failures: int = Field(
        10, ge=1, description="wrong API keys an address may send per minute; beyond, its "
                              "requests with a key get 429 until the minute has passed")
    s3_bucket: str = Field(
        "", description="S3-compatible bucket for job results (RQ workers upload a job's "
                        "files when it ends; the API streams them); empty: results stay in "
                        "the data directory")
    s3_prefix: str = Field("polydda/", description="key prefix of the results in the bucket")
    s3_endpoint_url: str = Field("", description="S3 endpoint (MinIO: http://minio:9000); "
                                                 "empty: AWS")
    s3_region: str = Field("", description="S3 region (empty: boto3's default)")
    trusted_proxies: Annotated[tuple[str, ...], NoDecode] = Field(
        (), description="reverse proxies (IP addresses or networks, e.g. 127.0.0.1 or "
                        "10.0.0.0/8) whose X-Forwarded-For names the client (for ownership "
                        "without keys, rate limits, the wrong-key throttle and the access "
                        "log) and whose X-Forwarded-Proto says the scheme; empty: the "
                        "headers are ignored, every client is the address it connects from")
    allow_open_network: bool = Field(
        False, description="let the service serve without API keys where loopback is not "
                           "certain: `polydda serve` on another address, or a launcher "
                           "whose address the app factory cannot know (uvicorn --factory); "
                           "every client that reaches it may then submit jobs, each sees "
                           "only the jobs of its own address")

    @field_validator("api_keys", "admin_keys", mode="before")
    @classmethod
    def _split_keys(cls, value: Any) -> Any:
        if isinstance(value, str):
            return frozenset(k.strip() for k in value.split(",") if k.strip())
        return value

    @field_validator("cors_origins", mode="before")
    @classmethod
    def _split_origins(cls, value: Any) -> Any:
        if isinstance(value, str):
            return tuple(o.strip() for o in value.split(",") if o.strip())
        return value

    @field_validator("trusted_proxies", mode="before")
    @classmethod
    def _split_proxies(cls, value: Any) -> Any:
        if isinstance(value, str):
            value = tuple(p.strip() for p in value.split(",") if p.strip())
        return value

    @field_validator("trusted_proxies")
    @classmethod
    def _proxy_networks(cls, value: tuple[str, ...]) -> tuple[str, ...]:
        import ipaddress

        for item in value:
            try:
                ipaddress.ip_network(item, strict=False)
            except ValueError:
                raise ValueError(f"{item!r} is not an IP address or network (e.g. "
                                 "127.0.0.1, 10.0.0.0/8, ::1)") from None
        return value

    @property
    def keys_required(self) -> bool:
        """True when requests need an X-API-Key (API or admin keys are configured)."""
        return bool(self.api_keys or self.admin_keys)

    @property
    def db_path(self) -> Path:
        return self.data_dir / "jobs.sqlite"

    def job_dir(self, job_id: str) -> Path:
        """Directory of one job's files (scene, results, plots)."""
        return self.data_dir / "jobs" / job_id

    def worker_env(self) -> dict[str, str]:
        """Environment a job process needs before numpy loads (thread counts)."""
        n = str(self.worker_threads)
        return {k: n for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS",
                               "NUMEXPR_NUM_THREADS", "NUMBA_NUM_THREADS")} | {"MPLBACKEND": "Agg"}


def limit_problems(scene: Any, settings: Settings) -> list[dict[str, str]]:
    """Service limits (stricter than the format's), each naming its setting: vertices,
    blocks (explicit ones plus the estimate of those the joints cut), duration, steps.

    Only counts and arithmetic on the validated scene: nothing is cut or built yet. The
    API checks them on every submission; `polydda validate --service-limits` on request.
    """
    from schemas.errors import fmt_count
    from schemas.scene import estimate_cut_blocks

    problems = []
    nv = sum(len(b.vertices) for b in scene.blocks)
    if scene.domain is not None and scene.domain.polyhedron is not None:
        nv += len(scene.domain.polyhedron.vertices)
    if nv > settings.max_vertices:
        problems.append({"loc": "blocks", "msg": f"the scene has {nv:,} vertices in all; this "
                         f"service accepts at most {settings.max_vertices:,} "
                         "(POLYDDA_MAX_VERTICES)"})
    if len(scene.blocks) > settings.max_blocks:
        problems.append({"loc": "blocks", "msg": f"{len(scene.blocks):,} blocks; this service "
                         f"accepts at most {settings.max_blocks:,} (POLYDDA_MAX_BLOCKS)"})
    elif scene.joints:
        cut = estimate_cut_blocks(scene)
        if cut + len(scene.blocks) > settings.max_blocks:
            extra = f" (and {len(scene.blocks):,} explicit ones)" if scene.blocks else ""
            problems.append({"loc": "joints", "msg": f"the joints would cut the domain into "
                             f"about {fmt_count(cut)} blocks{extra}; this service accepts at "
                             f"most {settings.max_blocks:,} (POLYDDA_MAX_BLOCKS): increase the "
                             "joint spacings or make the domain smaller"})
    a = scene.analysis
    # a staged run lasts its stages' total (analysis.duration is not used then)
    duration = sum(st.duration for st in scene.stages) if scene.stages else a.duration
    where = "stages" if scene.stages else "analysis.duration"
    what = "the stages last " if scene.stages else ""
    if duration > settings.max_duration:
        problems.append({"loc": where, "msg": f"{what}{duration:g} s; this service "
                         f"simulates at most {settings.max_duration:g} s "
                         "(POLYDDA_MAX_DURATION)"})
    if duration / a.time_step > settings.max_steps:
        problems.append({"loc": "analysis.time_step", "msg": f"duration / time_step = "
                         f"{duration / a.time_step:.3g} steps; this service runs at most "
                         f"{settings.max_steps:,} (POLYDDA_MAX_STEPS)"})
    return problems
