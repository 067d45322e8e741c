"""Job results in an S3-compatible object store (AWS S3, MinIO, ...), for workers on hosts
that share no file system with the API.

When `POLYDDA_S3_BUCKET` is set, an RQ worker uploads a job's directory (result.h5,
summary and the other artifacts; multipart above 8 MiB, boto3's transfer manager) to
`<prefix>jobs/<id>/` when the job ends, a `manifest.json` of the files last, and only then
records the job's outcome. The API streams downloads (Range requests too) from the store
and copies a job's files into its own data directory (a cache) the first time it needs
them whole (results document, plots, report, frames). Credentials and region come from
boto3's usual sources (AWS_ACCESS_KEY_ID / AWS_SECRET_ACCESS_KEY, ~/.aws, roles).
Without a bucket the data directory is the only store (the embedded default).
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: the object listing a job's files (name -> bytes), written after them: a job whose
#: manifest exists is stored whole
MANIFEST = "manifest.json"
#: multipart uploads above this size, in parts of this size
PART = 8 * 1024 * 1024


class ResultStore:
    """One bucket (and key prefix) of job results."""

    def __init__(self, bucket: str, prefix: str = "polydda/", endpoint_url: str = "",
                 region: str = "") -> None:
        import boto3
        from boto3.s3.transfer import TransferConfig
        from botocore.config import Config

        self.bucket, self.prefix = bucket, prefix
        self.client = boto3.client(
            "s3", endpoint_url=endpoint_url or None, region_name=region or None,
            config=Config(retries={"max_attempts": 5, "mode": "standard"},
                          s3={"addressing_style": "path"}))
        self.transfer = TransferConfig(multipart_threshold=PART, multipart_chunksize=PART)

    @classmethod
    def of(cls, settings: Any) -> ResultStore | None:
        """The store `settings` configure (None without a bucket)."""
        if not settings.s3_bucket:
            return None
        return cls(settings.s3_bucket, settings.s3_prefix, settings.s3_endpoint_url,
                   settings.s3_region)

    def key(self, job_id: str, name: str) -> str:
        return f"{self.prefix}jobs/{job_id}/{name}"

    # ------------------------------------------------------------------ writing
    def upload_job(self, job_id: str, job_dir: Path) -> dict[str, int]:
        """Upload every file of `job_dir` (not hidden temporaries), then the manifest;
        the manifest's {name: bytes}."""
        files: dict[str, int] = {}
        if job_dir.is_dir():
            for path in sorted(job_dir.rglob("*")):
                name = path.relative_to(job_dir).as_posix()
                if not path.is_file() or any(p.startswith(".") for p in name.split("/")):
                    continue
                self.client.upload_file(str(path), self.bucket, self.key(job_id, name),
                                        Config=self.transfer)
                files[name] = path.stat().st_size
        self.client.put_object(Bucket=self.bucket, Key=self.key(job_id, MANIFEST),
                               Body=json.dumps({"files": files}).encode(),
                               ContentType="application/json")
        return files

    def delete_job(self, job_id: str) -> None:
        """Remove a job's objects (its results were dismissed or expired)."""
        paginator = self.client.get_paginator("list_objects_v2")
        for page in paginator.paginate(Bucket=self.bucket, Prefix=self.key(job_id, "")):
            keys = [{"Key": o["Key"]} for o in page.get("Contents", [])]
            if keys:
                self.client.delete_objects(Bucket=self.bucket, Delete={"Objects": keys})

    # ------------------------------------------------------------------ reading
    def manifest(self, job_id: str) -> dict[str, int] | None:
        """The job's stored files {name: bytes} (None when the job is not stored)."""
        from botocore.exceptions import ClientError

        try:
            body = self.client.get_object(Bucket=self.bucket,
                                          Key=self.key(job_id, MANIFEST))["Body"].read()
        except ClientError as exc:
            if exc.response.get("Error", {}).get("Code") in ("NoSuchKey", "404"):
                return None
            raise
        return dict(json.loads(body)["files"])

    def fetch_job(self, job_id: str, job_dir: Path) -> bool:
        """Copy the job's stored files missing from `job_dir` there (each through a
        temporary file and a rename); False when the job is not stored."""
        files = self.manifest(job_id)
        if files is None:
            return False
        for name, size in files.items():
            path = job_dir / name
            if path.is_file() and path.stat().st_size == size:
                continue
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_name(f".{path.name}.{os.getpid()}.download")
            try:
                self.client.download_file(self.bucket, self.key(job_id, name), str(tmp),
                                          Config=self.transfer)
                os.replace(tmp, path)
            finally:
                with contextlib.suppress(FileNotFoundError):
                    tmp.unlink()
        return True

    def size(self, job_id: str, name: str) -> int | None:
        """Bytes of one stored file (None if the job has no such stored file)."""
        files = self.manifest(job_id)
        return None if files is None or name not in files else int(files[name])

    def stream(self, job_id: str, name: str, start: int | None = None,
               end: int | None = None) -> Iterator[bytes]:
        """The bytes `start`..`end` (inclusive; all without them) of a stored file, in
        chunks as they arrive."""
        kw: dict[str, Any] = {"Bucket": self.bucket, "Key": self.key(job_id, name)}
        if start is not None:
            kw["Range"] = f"bytes={start}-{'' if end is None else end}"
        body = self.client.get_object(**kw)["Body"]
        try:
            yield from body.iter_chunks(1 << 20)
        finally:
            body.close()
