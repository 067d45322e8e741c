"""`polydda` command line: the parser and the entry point.

Each subcommand is one `cmd_*` function in a module of this package (:mod:`.scenes`:
blocks, contacts, validate, schema; :mod:`.runs`: run, fos, le, seismic; :mod:`.analyses`:
kinematics, sweep; :mod:`.keyblocks`: keyblocks; :mod:`.orientations`: stereonet;
:mod:`.results`: plot, view, report; :mod:`.remote`: serve, worker, submit), taking the
parsed arguments and returning an exit code; add a command by writing one and registering it
in :func:`build_parser`. A command's module is imported only when that command runs.
Exit codes: 0 success, 3 a run that did not complete (its status and reason on stderr),
2 bad scene or bad arguments (problems on stderr, one per line),
1 an output file could not be written.
"""

from __future__ import annotations

import argparse
import importlib
import os
import shutil
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from service.cli.common import EXIT_OK, EXIT_SCENE, scene_failed
from service.jobs.worker import add_arguments as worker_options

__all__ = ["build_parser", "main"]

#: service.documents.SEARCH_DISTANCE_RATIO, written out: the parser imports no numpy
#: (tests/test_cli.py checks that the two agree)
SEARCH_DISTANCE_HELP = "contact search distance in m (default 0.001 x model size)"


class _ProcessIds:
    """The service's process ids (service.jobs.processes.PROCESS_IDS) as argparse choices,
    imported only when argparse checks or lists them (not for --version or --help)."""

    @staticmethod
    def _ids() -> tuple[str, ...]:
        from service.jobs.processes import PROCESS_IDS

        return PROCESS_IDS

    def __contains__(self, value: object) -> bool:
        return value in self._ids()

    def __iter__(self) -> Iterator[str]:
        return iter(self._ids())


def _command(module: str, name: str) -> Callable[[argparse.Namespace], int]:
    """The command `name` of `service.cli.<module>`, imported when it runs."""

    def command(args: argparse.Namespace) -> int:
        return int(getattr(importlib.import_module(f"service.cli.{module}"), name)(args))

    command.__name__ = command.__qualname__ = name
    return command


class _CommandList(argparse.HelpFormatter):
    """`polydda --help`: each command and its description on one line."""

    def __init__(self, prog: str) -> None:
        super().__init__(prog, max_help_position=16, width=max(80, min(
            120, shutil.get_terminal_size((80, 24)).columns)))
        # argparse measures the commands at their parent's indent, two short of their own:
        # `kinematics` (10 characters, indented 4) would go on a line of its own
        self._action_max_length = 14


class _Parser(argparse.ArgumentParser):
    """ArgumentParser whose usage errors print one line and exit with code 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.print_usage(sys.stderr)
        print(f"{self.prog}: {message}", file=sys.stderr)
        raise SystemExit(EXIT_SCENE)


def build_parser() -> argparse.ArgumentParser:
    """The argparse parser with one subparser per command (`func` set to its cmd_*)."""
    parser = _Parser(prog="polydda",
                     description="3-D Discontinuous Deformation Analysis of rock blocks",
                     formatter_class=_CommandList)
    parser.add_argument("--version", action="version", version=f"polydda {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)

    add_parser = sub.add_parser

    def described(name: str, **kwargs: Any) -> argparse.ArgumentParser:
        """A command's parser; its one-line help heads `polydda COMMAND --help` too when it
        has no longer description."""
        kwargs.setdefault("description", kwargs.get("help"))
        return add_parser(name, **kwargs)

    sub.add_parser = described  # type: ignore[method-assign]

    p = sub.add_parser("blocks", help="list the blocks of a scene (after cutting)")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--export", metavar="FILE", help="write the blocks to FILE (.obj or .vtk)")
    p.set_defaults(func=_command("scenes", "cmd_blocks"))

    p = sub.add_parser("contacts", help="list the contact constraints of a scene as given")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--search-distance", type=float, metavar="M",
                   help=SEARCH_DISTANCE_HELP)
    p.set_defaults(func=_command("scenes", "cmd_contacts"))

    p = sub.add_parser("validate", help="check a scene and report every problem")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true",
                   help="print one JSON document (valid, blocks, warnings, problems)")
    p.add_argument("--service-limits", action="store_true",
                   help="also check a server's size limits (POLYDDA_MAX_BLOCKS, "
                        "POLYDDA_MAX_VERTICES, POLYDDA_MAX_DURATION, POLYDDA_MAX_STEPS; "
                        "stricter than the format's), as `polydda submit` would meet them")
    p.set_defaults(func=_command("scenes", "cmd_validate"))

    p = sub.add_parser("run", help="run the simulation of a scene")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--out", required=True, metavar="RESULT.h5", help="HDF5 result file")
    p.add_argument("--summary", metavar="SUMMARY.json", help="also write a JSON summary")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.add_argument("--json", action="store_true",
                   help="print the summary as one JSON document (no progress output)")
    p.add_argument("--checkpoints", metavar="DIR", help="a staged run saves the state at "
                   "each stage's end here as stage-<k>.npz (default: RESULT.h5.stages)")
    p.add_argument("--resume-from", metavar="STAGE.npz", help="continue a staged run from "
                   "the end of a stage (its checkpoint; the scene may change later stages)")
    p.set_defaults(func=_command("runs", "cmd_run"))

    p = sub.add_parser("fos", help="factor of safety by strength reduction")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_command("runs", "cmd_fos"))

    p = sub.add_parser("le", help="limit equilibrium of a planar block or a two-plane wedge",
                       description="the vector method (Hoek & Bray; Low 1997) on the scene's "
                                   "one free block: cohesion, water, bolts and tendons, "
                                   "seismic kh / kv, point loads; exit 2 saying why when it "
                                   "does not apply")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=_command("runs", "cmd_le"))

    p = sub.add_parser("seismic", help="critical (yield) seismic coefficient kh by bisection")
    p.add_argument("scene", help="scene JSON file (its 'seismic' gives azimuth and kv)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_command("runs", "cmd_seismic"))
    p = sub.add_parser("kinematics", help="kinematic screening (Markland tests, stereonet)",
                       description="planar and wedge sliding, flexural and direct toppling "
                                   "of the scene's joints against its slope_face")
    p.add_argument("scene", help="scene JSON file (with a slope_face)")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.add_argument("--plot", metavar="OUT.png", help="write the stereonet to this PNG file")
    p.set_defaults(func=_command("analyses", "cmd_kinematics"))

    p = sub.add_parser("keyblocks", help="key blocks of the excavations, what a run did to them",
                       description="key blocks of the scene's excavations (block theory: "
                                   "removable, mode, factor of safety; fixed blocks are the "
                                   "rock mass beyond the model, never key blocks) and, with "
                                   "--result, what the DDA run did to each after its "
                                   "excavation")
    p.add_argument("scene", help="scene JSON file with excavations")
    p.add_argument("--result", metavar="RESULT.h5", help="the scene's run: each block's "
                   "final displacement and the DDA's verdict")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=_command("keyblocks", "cmd_keyblocks"))

    p = sub.add_parser(
        "stereonet", help="measured orientations: pole density, sets, Fisher κ",
        description="read dip / dip direction measurements (CSV), contour their poles' "
                    "density on an equal-area stereonet, pick the sets (k-means on the "
                    "sphere) and fit each one's Fisher mean, κ and 95 % cone; with --scene "
                    "and --out, write them as the scene's joints (and with --sweep, as the "
                    "sweep's Fisher parameters of their orientation)")
    p.add_argument("measurements", help="CSV file: columns dip, dip_direction (degrees)")
    p.add_argument("--sets", type=int, default=2, metavar="K",
                   help="number of joint sets to pick (default 2)")
    p.add_argument("--seed", type=int, default=0, help="seed of the k-means starts")
    p.add_argument("--names", metavar="A,B",
                   help="names of the sets, largest first (default J1, J2, ...)")
    p.add_argument("--plot", metavar="OUT.png",
                   help="the stereonet (default: MEASUREMENTS_stereonet.png beside the CSV)")
    p.add_argument("--scene", metavar="SCENE.json", help="a scene to write the sets into")
    p.add_argument("--out", metavar="NEW.json", help="where the scene with the sets goes")
    p.add_argument("--spacing", type=float, metavar="M",
                   help="spacing of joints added to the scene (default: one plane each)")
    p.add_argument("--sweep", action="store_true",
                   help="also add the sets' Fisher κ to the scene's sweep.parameters")
    p.add_argument("--json", action="store_true", help="print one JSON document")
    p.set_defaults(func=_command("orientations", "cmd_stereonet"))

    p = sub.add_parser(
        "sweep", help="sweep or Monte Carlo analysis: probability of failure",
        description="N realisations of the scene's parameters (the scene's sweep.parameters, "
                    "or --parameter, or the joints' friction angle by --friction-mean / "
                    "--friction-sd): each a distribution (normal, uniform, lognormal; Fisher "
                    "for a joint orientation) drawn from the seed, or a list of values (a "
                    "study); a factor of safety each, the probability of failure, FS "
                    "histogram and CDF and the sensitivity of FS to each parameter; "
                    "re-running with the same --out skips the realisations already done")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--n", type=int, help="realisations (default: the scene's sweep.n, or 200)")
    p.add_argument("--seed", type=int, help="random seed (default: sweep.seed, or 0)")
    p.add_argument("--friction-mean", type=float, metavar="DEG",
                   help="mean friction angle (default: sweep.friction_angle.mean)")
    p.add_argument("--friction-sd", type=float, metavar="DEG",
                   help="its standard deviation (default: sweep.friction_angle.sd)")
    p.add_argument("--parameter", action="append", metavar="NAME=JSON",
                   help="a parameter of the sweep, as in the scene's sweep.parameters, e.g. "
                        "'cohesion={\"distribution\": \"uniform\", \"low\": 0, \"high\": "
                        "20000}' (Pa; angles in degrees); repeat for several")
    p.add_argument("--mode", choices=("dda", "analytic"),
                   help="dda: the engine's strength reduction per realisation; analytic: "
                        "limit equilibrium (a planar block or a two-plane wedge, with "
                        "everything the scene has; refused, exit 2, where it does not apply)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder of the sweep")
    p.add_argument("--workers", type=int, default=1, help="processes (default 1)")
    p.add_argument("--server", metavar="URL",
                   help="run the sweep as one job of this PolyDDA service fanned out in "
                        "--jobs child jobs (embedded workers or `polydda worker`s); the "
                        "server merges them")
    p.add_argument("--jobs", type=int, default=2, metavar="K",
                   help="child jobs (shares) of the sweep on --server (default 2)")
    p.add_argument("--api-key", help="API key for --server, if it requires one")
    p.add_argument("--limit", type=int, metavar="K",
                   help="evaluate at most K new realisations, then aggregate those done")
    p.add_argument("--json", action="store_true", help="print the aggregate as JSON")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_command("analyses", "cmd_sweep"))

    p = sub.add_parser("plot", help="PNG plots of a result file")
    p.add_argument("result", help="HDF5 result file")
    p.add_argument("--out", metavar="DIR", help="output folder (default: beside the result)")
    p.add_argument("--blocks", metavar="NAMES", action="append",
                   help="blocks in the histories, by name (comma-separated or repeated; "
                        "default: the free blocks that moved most, at most 8)")
    p.add_argument("--time", metavar="SECONDS", action="append",
                   help="3-D snapshot at the recorded step nearest this time (comma-separated "
                        "or repeated; default: initial and final)")
    p.add_argument("--step", metavar="N", action="append",
                   help="3-D snapshot at this recorded solver step (comma-separated or "
                        "repeated)")
    p.set_defaults(func=_command("results", "cmd_plot"))

    p = sub.add_parser("view", help="the 3-D viewer of a local result file, or the scene "
                       "builder, in the browser",
                       description="serve the viewer (and the report) of RESULT.h5 on a local "
                                   "port and open it in the browser, with the scene builder "
                                   "at /builder; without RESULT.h5, the service on a "
                                   "temporary folder opened at the scene builder (its scenes "
                                   "run as jobs there); Ctrl-C stops it")
    p.add_argument("result", nargs="?", help="HDF5 result file (polydda run --out); omit it "
                                             "to build a scene")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument("--port", type=int, default=0, help="port (default: any free one)")
    p.add_argument("--no-browser", action="store_true",
                   help="print the address only; do not open a browser")
    p.add_argument("--max-frames", type=int, default=2000, metavar="N",
                   help="recorded steps the viewer loads at most (every k-th beyond)")
    p.set_defaults(func=_command("results", "cmd_view"))

    p = sub.add_parser("report", help="the printable report of a local result file",
                       description="write the report of RESULT.h5 (conclusion, moving "
                                   "blocks, plots, the scene) as one HTML file with its "
                                   "figures inline, and a PDF of it when a Chromium is found")
    p.add_argument("result", help="HDF5 result file (polydda run --out)")
    p.add_argument("--out", metavar="REPORT.html",
                   help="HTML file to write (default: the result's name with .html); the "
                        "PDF goes beside it")
    p.add_argument("--threshold", type=float, metavar="M",
                   help="a free block that moved less than this many metres has not moved "
                        "(default 0.01)")
    p.add_argument("--no-pdf", action="store_true", help="write the HTML only")
    p.set_defaults(func=_command("results", "cmd_report"))

    p = sub.add_parser("serve", help="start the REST API and its embedded workers")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on")
    p.add_argument("--port", type=int, default=8000, help="port (default 8000)")
    p.set_defaults(func=_command("remote", "cmd_serve"))

    p = sub.add_parser("worker", help="start a scale-out worker (Redis queue)",
                       description="work PolyDDA jobs from the Redis queue; each option "
                                   "overrides its POLYDDA_* variable")
    worker_options(p)
    p.set_defaults(func=_command("remote", "cmd_worker"))

    p = sub.add_parser("submit", help="submit a scene to a running server")
    p.add_argument("scene", help="scene JSON file")
    p.add_argument("--url", default="http://127.0.0.1:8000", help="server URL")
    p.add_argument("--process", choices=_ProcessIds(), metavar="PROCESS",
                   help="%(choices)s (default: from the scene's analysis.type)")
    p.add_argument("--api-key", help="API key, if the server requires one")
    p.add_argument("--wait", action="store_true", help="follow the job to its end")
    p.add_argument("--retries", type=int, default=5, metavar="N",
                   help="retries of a submission answered 429 / 503 or cut off, after the "
                        "server's Retry-After (same Idempotency-Key: never two jobs; "
                        "default 5)")
    p.set_defaults(func=_command("remote", "cmd_submit"))

    p = sub.add_parser("warm-up", help="compile the engine's kernels ahead, on every core",
                       description="compile the engine's numba kernels into their cache "
                                   "before the first run (a few steps of the paper's wedge "
                                   "in parallel processes, each compiling its share), so that "
                                   "the first `polydda run` starts at once; nothing to do "
                                   "when they are cached")
    p.add_argument("--workers", type=int, metavar="N",
                   help="processes at once (default: the cores)")
    p.add_argument("--json", action="store_true",
                   help="print what each process compiled and the seconds it took")
    p.set_defaults(func=_command("warmup", "cmd_warm_up"))

    p = sub.add_parser("schema", help="print the JSON Schema of the scene format")
    p.set_defaults(func=_command("scenes", "cmd_schema"))
    return parser


def _version() -> str:
    """The installed package's version (the source tree's when not installed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("polydda")
    except PackageNotFoundError:
        from service.api.app import VERSION

        return VERSION


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of `polydda`; returns the exit code."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help or a usage error
        return int(exc.code or 0)
    from schemas.errors import SceneError  # pydantic: after --help / --version

    try:
        return int(args.func(args))
    except SceneError as exc:  # any command that builds a scene: problems, exit 2
        return scene_failed(exc)
    except BrokenPipeError:  # output piped into a reader that closed early (`| head`)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return EXIT_OK


if __name__ == "__main__":
    sys.exit(main())
