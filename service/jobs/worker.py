"""`polydda worker`: a scale-out worker taking jobs from the Redis queue (RQ backend).

Start any number of them on any machines that share the data directory with the API:
`POLYDDA_REDIS_URL=redis://host:6379/0 POLYDDA_DATA_DIR=/shared/polydda polydda worker`.
The options are declared once (:func:`add_arguments`) for both `polydda worker` and
`python -m service.jobs.worker`.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

LOG_LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR")


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The worker's options (each overrides its POLYDDA_* variable) on parser `p`."""
    p.add_argument("--redis-url", metavar="URL", help="Redis URL (POLYDDA_REDIS_URL)")
    p.add_argument("--queue", help="queue name (POLYDDA_RQ_QUEUE)")
    p.add_argument("--data-dir", metavar="DIR",
                   help="results directory shared with the API (POLYDDA_DATA_DIR)")
    p.add_argument("--name", help="worker name (default: RQ's)")
    p.add_argument("--burst", action="store_true", help="stop when the queue is empty")
    p.add_argument("--max-jobs", type=_positive_int, metavar="N",
                   help="stop after this many jobs")
    p.add_argument("--log-level", default="INFO", type=str.upper, choices=LOG_LEVELS,
                   help="logging level (default INFO)")


def build_parser() -> argparse.ArgumentParser:
    """Arguments of `python -m service.jobs.worker` (the same as `polydda worker`)."""
    p = argparse.ArgumentParser(prog="polydda worker",
                                description="work PolyDDA jobs from the Redis queue")
    add_arguments(p)
    return p


def argv_of(args: argparse.Namespace) -> list[str]:
    """The command-line options that :func:`build_parser` parses back into `args`."""
    argv: list[str] = []
    for dest in ("redis_url", "queue", "data_dir", "name", "max_jobs"):
        value = getattr(args, dest)
        if value is not None:
            argv += ["--" + dest.replace("_", "-"), str(value)]
    if args.burst:
        argv.append("--burst")
    return [*argv, "--log-level", args.log_level]


def run(args: argparse.Namespace) -> int:
    """Run one RQ worker until it is stopped (or the queue is empty with --burst).

    Redis must answer at the start; later outages are ridden out (reconnecting with
    backoff, service.jobs.rq_worker). Exit code 0; 2 for a malformed Redis URL; 1 when
    Redis cannot be reached at the start.
    """
    from service.settings import Settings

    overrides = {k: v for k, v in (("redis_url", args.redis_url), ("rq_queue", args.queue),
                                   ("data_dir", args.data_dir)) if v is not None}
    settings = Settings(**overrides)
    # thread counts must be in the environment before numpy loads, and the job function
    # reads its settings from the environment inside the work horse
    env = {**settings.worker_env(), "POLYDDA_DATA_DIR": str(settings.data_dir.resolve()),
           "POLYDDA_PROGRESS_INTERVAL": str(settings.progress_interval)}
    if any(os.environ.get(k) != v for k, v in env.items()):
        # become a fresh `python -m service.jobs.worker` (same pid) started with `env`: numpy
        # (and its BLAS thread pool) must not be loaded yet, and the work horses it forks
        # show the thread counts in their environment (/proc/PID/environ), not only in
        # os.environ
        sys.stdout.flush()
        sys.stderr.flush()
        os.execve(sys.executable, [sys.executable, "-m", "service.jobs.worker", *argv_of(args)],
                  {**os.environ, **env})
    os.environ.update(env)
    logging.basicConfig(level=args.log_level, stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    # load the engine once here; each job's work horse is a fork of this process
    from redis import Redis
    from redis.exceptions import ConnectionError as RedisConnectionError
    from rq import Queue

    import engine.results.reader  # noqa: F401
    import engine.results.writer  # noqa: F401
    import engine.step.simulation  # noqa: F401
    import schemas.convert  # noqa: F401
    import service.jobs.execute  # noqa: F401
    from service.jobs.rq_worker import PolyddaWorker

    try:
        conn = Redis.from_url(settings.redis_url, socket_connect_timeout=5)
    except ValueError as exc:
        print(f"polydda worker: bad Redis URL {settings.redis_url!r}: {exc}", file=sys.stderr)
        return 2
    try:
        conn.ping()
    except RedisConnectionError as exc:
        print(f"polydda worker: cannot reach Redis at {settings.redis_url}: {exc}",
              file=sys.stderr)
        return 1
    worker = PolyddaWorker([Queue(settings.rq_queue, connection=conn)], connection=conn,
                           name=args.name)
    worker.work(burst=args.burst, max_jobs=args.max_jobs, logging_level=args.log_level)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `python -m service.jobs.worker`; returns the exit code."""
    return run(build_parser().parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
