"""Prefect flows that stage DriveTrack Release on Dask (thin task wrappers around the core).

Importing this package sets quiet, project-local defaults for Prefect and Dask *before* Prefect
is imported (Prefect reads its settings at import): ``PREFECT_HOME`` under ``REPO/.prefect/``, no
telemetry, Dask logs at warning. Values already in the environment win.

``REPO`` is the checkout when the flows run from one (``pip install -e .`` or ``PYTHONPATH``);
installed from a wheel (``pip install .``) it is the working directory of the process, so that
the defaults (``.prefect/``, ``build/``, ``store/``, ``data/synthetic``) never land inside
site-packages.
"""
import os
from pathlib import Path


def _project_root() -> Path:
    here = Path(__file__).resolve().parents[1]
    if (here / "pyproject.toml").is_file() and (here / "drivetrack").is_dir():
        return here
    return Path.cwd()


REPO = _project_root()

os.environ.setdefault("PREFECT_HOME", str(REPO / ".prefect"))
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
