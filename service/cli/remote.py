"""Service commands: `polydda serve` (REST API), `worker` (scale-out worker on the Redis
queue) and `submit` (a scene to a running server)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.cli.common import EXIT_IO, EXIT_OK, EXIT_SCENE, print_json


def cmd_serve(args: argparse.Namespace) -> int:
    """Start the REST API with its embedded workers (or the RQ backend, by settings); exit
    code 1 when another server owns the data directory."""
    from service.api.app import serve

    return serve(args.host, args.port)


def cmd_worker(args: argparse.Namespace) -> int:
    """Start one scale-out worker on the Redis queue (options: service.jobs.worker)."""
    from service.jobs.worker import run as run_worker

    return run_worker(args)


def cmd_submit(args: argparse.Namespace) -> int:
    """Submit a scene to a running server; with --wait, follow it to the end."""
    from schemas.scene import load_scene  # the scene's format, checked here (nothing cut)
    from service.cli.client import ServiceError, Unreachable, print_status, submit

    if not Path(args.scene).is_file():
        print(f"polydda submit: no such scene file: {args.scene}", file=sys.stderr)
        return EXIT_SCENE
    load_scene(Path(args.scene))  # SceneError (exit 2) before anything is sent
    try:
        doc = submit(args.url, args.scene, wait=args.wait, process=args.process,
                     api_key=args.api_key, on_status=print_status, retries=args.retries)
    except Unreachable as exc:
        print(f"polydda submit: {exc}", file=sys.stderr)
        return EXIT_IO
    except ServiceError as exc:
        print(str(exc), file=sys.stderr)
        return EXIT_SCENE
    print_json(doc)
    return EXIT_OK if doc.get("status") in ("successful", "accepted", "running") else EXIT_IO

