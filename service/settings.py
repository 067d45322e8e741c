"""Service settings: one pydantic-settings object, read from `POLYDDA_*` environment variables.

Example: `POLYDDA_DATA_DIR=/data POLYDDA_BACKEND=rq POLYDDA_REDIS_URL=redis://redis:6379/0`.
`POLYDDA_API_KEYS` is a comma-separated list (empty: no key needed).
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
        frozenset(), description="accepted X-API-Key values; empty: keys are not checked")
    client_quota: int = Field(16, ge=1,
                              description="unfinished (accepted or running) jobs per client")
    worker_threads: int = Field(1, ge=1, description="OMP/BLAS threads of a job process")
    worker_nice: int = Field(5, ge=0, le=19, description="niceness of job processes")
    progress_interval: float = Field(0.25, gt=0, description="s between progress writes")
    cancel_grace: float = Field(1.0, ge=0,
                                description="s a cancelled job may take before it is killed")
    max_attempts: int = Field(2, ge=1,
                              description="runs of a job interrupted by a service restart")
    job_timeout: int = Field(7 * 24 * 3600, ge=1, description="RQ job timeout (s)")

    @field_validator("api_keys", mode="before")
    @classmethod
    def _split_keys(cls, value: Any) -> Any:
        if isinstance(value, str):
            return frozenset(k.strip() for k in value.split(",") if k.strip())
        return value

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
                               "NUMEXPR_NUM_THREADS")} | {"MPLBACKEND": "Agg"}
