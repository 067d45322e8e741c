"""`polydda worker`: a scale-out worker taking jobs from the Redis queue (RQ backend).

Start any number of them on any machines that share the data directory with the API:
`POLYDDA_REDIS_URL=redis://host:6379/0 POLYDDA_DATA_DIR=/shared/polydda polydda worker`.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Sequence

from service.settings import Settings


def build_parser() -> argparse.ArgumentParser:
    """Arguments of `polydda worker` (each overrides its POLYDDA_* variable)."""
    p = argparse.ArgumentParser(prog="polydda worker",
                                description="work PolyDDA jobs from the Redis queue")
    p.add_argument("--redis-url", help="Redis URL (POLYDDA_REDIS_URL)")
    p.add_argument("--queue", help="queue name (POLYDDA_RQ_QUEUE)")
    p.add_argument("--data-dir", help="shared results directory (POLYDDA_DATA_DIR)")
    p.add_argument("--name", help="worker name (default: RQ's)")
    p.add_argument("--burst", action="store_true", help="stop when the queue is empty")
    p.add_argument("--max-jobs", type=int, help="stop after this many jobs")
    p.add_argument("--log-level", default="INFO", help="logging level (default INFO)")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run one RQ worker until it is stopped (or the queue is empty with --burst)."""
    args = build_parser().parse_args(argv)
    overrides = {k: v for k, v in (("redis_url", args.redis_url), ("rq_queue", args.queue),
                                   ("data_dir", args.data_dir)) if v is not None}
    settings = Settings(**overrides)
    # the job function reads its settings from the environment inside the work horse
    os.environ.update(settings.worker_env())
    os.environ["POLYDDA_DATA_DIR"] = str(settings.data_dir.resolve())
    os.environ["POLYDDA_PROGRESS_INTERVAL"] = str(settings.progress_interval)
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")

    # load the engine once here; each job's work horse is a fork of this process
    from redis import Redis
    from rq import Queue, Worker

    import engine.results  # noqa: F401
    import engine.simulation  # noqa: F401
    import schemas.convert  # noqa: F401
    import service.jobs  # noqa: F401

    conn = Redis.from_url(settings.redis_url)
    worker = Worker([Queue(settings.rq_queue, connection=conn)], connection=conn,
                    name=args.name)
    worker.work(burst=args.burst, max_jobs=args.max_jobs,
                logging_level=args.log_level.upper())
    return 0


if __name__ == "__main__":
    sys.exit(main())
