"""The version of PolyDDA: the installed distribution's, else the source tree's
pyproject.toml (a checkout used without `pip install`)."""

from __future__ import annotations

from pathlib import Path


def version() -> str:
    """The version string, e.g. `0.1.0`."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as installed

    try:
        return installed("polydda")
    except PackageNotFoundError:
        import tomllib

        pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
        with pyproject.open("rb") as f:
            return str(tomllib.load(f)["project"]["version"])
