"""Options shared by the release subcommands (publish, verify, versions, diff, gc)."""
from __future__ import annotations

import json


def add_store_options(p) -> None:
    p.add_argument("--dataset", default="drivetrack-waymo", help="dataset name (folder under the store)")
    p.add_argument("--endpoint-url", default=None,
                   help="S3-compatible endpoint (else AWS_ENDPOINT_URL / AWS config); s3:// stores only")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def storage_options(args) -> dict | None:
    if getattr(args, "endpoint_url", None):
        return {"client_kwargs": {"endpoint_url": args.endpoint_url}}
    return None


def print_json(obj) -> None:
    print(json.dumps(obj, indent=1, sort_keys=True, default=str))
