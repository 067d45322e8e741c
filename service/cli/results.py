"""Result commands: `polydda plot` (PNG plots of an HDF5 result)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from service.cli.common import EXIT_IO, EXIT_OK, EXIT_SCENE, listed, open_result_file


def cmd_plot(args: argparse.Namespace) -> int:
    """PNG plots of a result file: histories, energy, displacement components, snapshots."""
    from engine.results.plots import plot_all, snapshot_steps  # matplotlib only when plotting

    blocks = listed(args.blocks)
    try:
        times = None if args.time is None else [float(t) for t in listed(args.time) or []]
        steps = None if args.step is None else [int(n) for n in listed(args.step) or []]
    except ValueError as exc:
        print(f"--time / --step: not a number: {exc}", file=sys.stderr)
        return EXIT_SCENE
    result = open_result_file("plot", args.result)
    if isinstance(result, int):
        return result
    with result:
        try:  # the choices, against the file: bad arguments exit 2
            for b in blocks or []:
                result.block_index(b)
            snapshot_steps(result, times, steps)
        except (KeyError, ValueError) as exc:
            names = ", ".join(result.block_names)
            hint = f" (blocks: {names})" if isinstance(exc, KeyError) else ""
            print(f"{exc.args[0] if exc.args else exc}{hint}", file=sys.stderr)
            return EXIT_SCENE
        try:
            paths = plot_all(result, args.out, blocks=blocks, times=times, steps=steps)
        except (OSError, KeyError, ValueError) as exc:
            print(f"cannot plot {args.result}: {exc}", file=sys.stderr)
            return EXIT_IO
    for p in paths:
        print(p)
    return EXIT_OK



# --------------------------------------------------------------------------- view, report

#: browsers that print a page to PDF headless, in the order they are looked for
CHROMIUMS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")


def cmd_view(args: argparse.Namespace) -> int:
    """Serve the service's 3-D viewer for a local result file on a local port and open it
    in the browser (until Ctrl-C); its scene builder too (`/builder`). Without a result:
    the service itself on a temporary data directory, opened at the scene builder, whose
    scenes then run as jobs."""
    import socket
    import webbrowser

    import uvicorn

    if args.result is None:
        from service.api.app import is_loopback

        if not is_loopback(args.host):
            print(f"polydda view: the scene builder runs jobs: it listens on loopback only "
                  f"(not {args.host}); use polydda serve with API keys to share it",
                  file=sys.stderr)
            return EXIT_SCENE
        app, page, work = _builder_service(args.host)
    else:
        result = open_result_file("view", args.result)
        if isinstance(result, int):
            return result
        result.close()
        from service.api.local import local_app

        app = local_app(Path(args.result), max_frames=args.max_frames)
        page = next(r.path for r in app.routes if getattr(r, "path", "").endswith("/viewer"))
        work = None
    try:
        sock = socket.create_server((args.host, args.port))
    except OSError as exc:
        print(f"polydda view: cannot listen on {args.host}:{args.port}: "
              f"{exc.strerror or exc}", file=sys.stderr)
        return EXIT_IO
    port = sock.getsockname()[1]
    url = f"http://{args.host}:{port}{page}"
    if args.result is None:
        print(f"scene builder: {url}\njobs and results: {work} (removed when it stops)\n"
              "(Ctrl-C stops the server)", flush=True)
    else:
        base = url.removesuffix("/viewer")
        print(f"viewer: {url}\nreport: {base}/report\nscene builder: "
              f"http://{args.host}:{port}/builder\n(Ctrl-C stops the server)", flush=True)
    if not args.no_browser:
        webbrowser.open(url)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    try:
        server.run(sockets=[sock])
    except KeyboardInterrupt:
        pass
    finally:
        sock.close()
        if work is not None:
            import shutil

            shutil.rmtree(work, ignore_errors=True)
    return EXIT_OK


def _builder_service(host: str) -> tuple[object, str, Path]:
    """The REST service on a temporary data directory (its jobs go when `view` stops),
    listening on `host` (loopback: `view` refuses any other), and the path of its builder
    page."""
    import tempfile

    from service.api.app import create_app
    from service.settings import Settings

    work = Path(tempfile.mkdtemp(prefix="polydda-view-"))
    return (create_app(Settings(data_dir=work, min_free_bytes=0), listen=host), "/builder",
            work)


def cmd_report(args: argparse.Namespace) -> int:
    """The printable report of a local result file as one HTML file (plots inline), and a
    PDF of it when a Chromium is there to print it."""
    result = open_result_file("report", args.result)
    if isinstance(result, int):
        return result
    result.close()
    from service.api.local import write_report

    source = Path(args.result)
    out = Path(args.out) if args.out else source.with_suffix(".html")
    if args.threshold is not None and not args.threshold > 0:
        print("--threshold: must be a positive length in m", file=sys.stderr)
        return EXIT_SCENE
    try:
        write_report(source, out, args.threshold)
    except OSError as exc:
        print(f"polydda report: cannot write {out}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_IO
    print(f"written: {out}")
    if args.no_pdf:
        return EXIT_OK
    pdf = out.with_suffix(".pdf")
    note = print_pdf(out, pdf)
    print(f"written: {pdf}" if note is None else f"no PDF: {note}",
          file=sys.stdout if note is None else sys.stderr)
    return EXIT_OK


def print_pdf(html: Path, pdf: Path, timeout: float = 180.0) -> str | None:
    """Print `html` to `pdf` with a headless Chromium; None when done, else why not."""
    import shutil
    import subprocess

    browser = next((b for b in map(shutil.which, CHROMIUMS) if b), None)
    if browser is None:
        return ("no Chromium found (" + ", ".join(CHROMIUMS) + "); open the HTML report in a "
                "browser and print it to PDF (its Print button)")
    pdf.unlink(missing_ok=True)
    cmd = [browser, "--headless", "--disable-gpu", "--no-sandbox", "--no-pdf-header-footer",
           f"--print-to-pdf={pdf.resolve()}", html.resolve().as_uri()]
    try:
        subprocess.run(cmd, capture_output=True, timeout=timeout, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"{Path(browser).name} did not print the report: {exc}"
    if not pdf.is_file() or pdf.read_bytes()[:4] != b"%PDF":
        return f"{Path(browser).name} did not print the report to {pdf}"
    return None
