"""Prefect flows that stage DriveTrack Release on Dask (thin task wrappers around the core).

Importing this package sets quiet, project-local defaults for Prefect and Dask *before* Prefect
is imported (Prefect reads its settings at import): ``PREFECT_HOME`` under the repository's
``.prefect/``, no telemetry, Dask logs at warning. Values already in the environment win.
"""
import os
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

os.environ.setdefault("PREFECT_HOME", str(REPO / ".prefect"))
os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
