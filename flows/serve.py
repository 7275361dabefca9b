"""Scheduled regeneration: serve the ``release`` flow as a deployment with a cron schedule.

    python -m flows.serve [--cron "0 3 * * *"] [--source URL] [--store URL]      (make serve)

Each scheduled run builds version ``auto``: the next patch version when the source data, the
configuration or the code changed since the latest release, and nothing otherwise (the release
fingerprint, see drivetrack/release/keys.py). The same deployment is declared for ``prefect deploy`` in
infra/prefect.yaml. Against a Prefect server or Cloud, set PREFECT_API_URL (and PREFECT_API_KEY)
first; against a remote Dask cluster, set DRIVETRACK_DASK_ADDRESS (docs/orchestration.md).
"""
from __future__ import annotations

import argparse
import os
import sys

from flows import REPO

DEPLOYMENT_NAME = "scheduled-regeneration"
DEFAULT_CRON = "0 3 * * *"


def deployment_parameters(source: str | None = None, store: str | None = None) -> dict:
    return {"version": "auto",
            "source": source or os.environ.get("DRIVETRACK_SOURCE") or str(REPO / "data" / "synthetic"),
            "store": store or os.environ.get("DRIVETRACK_STORE") or str(REPO / "store"),
            "splits": ["training"], "skip_unchanged": True}


def build_deployment(cron: str | None = None, source: str | None = None, store: str | None = None):
    """The RunnerDeployment ``release/scheduled-regeneration`` (no API call until served)."""
    from flows.release import release

    from prefect.deployments.runner import EntrypointType

    return release.to_deployment(
        name=DEPLOYMENT_NAME, entrypoint_type=EntrypointType.MODULE_PATH, cron=cron or os.environ.get("DRIVETRACK_CRON") or DEFAULT_CRON,
        parameters=deployment_parameters(source, store), tags=["drivetrack", "release"],
        description="Regenerate the release when the source data, the configuration or the code changed.")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m flows.serve", description=__doc__.split("\n\n")[0])
    p.add_argument("--cron", default=None, help=f"cron schedule (default $DRIVETRACK_CRON or {DEFAULT_CRON!r})")
    p.add_argument("--source", default=None)
    p.add_argument("--store", default=None)
    args = p.parse_args(argv)
    from flows.release import release, synthesize_default_source
    from prefect.deployments.runner import EntrypointType

    from flows.runtime import prefect_api

    source = args.source or os.environ.get("DRIVETRACK_SOURCE") or synthesize_default_source(REPO / "data" / "synthetic")
    store = args.store if not args.store or "://" in args.store else os.path.abspath(args.store)
    params = deployment_parameters(source, store)
    cron = args.cron or os.environ.get("DRIVETRACK_CRON") or DEFAULT_CRON
    with prefect_api(full=True) as url:
        print(f"serving release/{DEPLOYMENT_NAME} on cron {cron!r} against {url} with {params} (Ctrl-C stops; "
              f"the deployment is not paused on shutdown)", flush=True)
        release.serve(name=DEPLOYMENT_NAME, cron=cron, parameters=params, pause_on_shutdown=False,
                      entrypoint_type=EntrypointType.MODULE_PATH, tags=["drivetrack", "release"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
