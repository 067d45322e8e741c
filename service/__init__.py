"""PolyDDA's service layer: the `polydda` command line and the REST service around the engine.

- :mod:`service.cli`: the command line (`polydda ...`) and the REST client it submits with;
- :mod:`service.api`: HTTP — the FastAPI app, thin routes, problems, OpenAPI, metrics, and
  the pages for people (home, 3-D viewer, report) with the viewer's frames;
- :mod:`service.jobs`: the job store (SQLite), the backends that run jobs (embedded
  processes, or RQ + Redis workers), the process registry and the job function, sweeps
  fanned out over the queue;
- :mod:`service.sweep` (sweeps over a scene's parameters), :mod:`service.documents` (the
  documents both the CLI and the API answer with) and :mod:`service.settings` (one settings
  object) serve all three.

Imports run cli → api → jobs → sweep → documents, settings (import contracts in
pyproject.toml).
"""
