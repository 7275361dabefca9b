"""Options, exit codes and error reporting shared by the store subcommands (publish, verify,
versions, diff, gc, status) and ``info``."""
from __future__ import annotations

import json
import os
import sys

EXIT_OK = 0
EXIT_FAILED = 1
"""The command ran and found a problem: verify found missing, extra or corrupt files; publish was
refused (version exists, another publish holds it) or interrupted."""
EXIT_BAD_INPUT = 2
"""Bad input: an invalid dataset or version name, a version that is not published, an unreadable
manifest, a bad option."""
EXIT_GATES_FAILED = 3
"""publish only: the quality gates failed and no --accept-failed-gates reason was given."""
EXIT_UNREACHABLE = 4
"""The store (or a source URL) cannot be reached: connection refused or timed out, unknown host,
missing credentials, permission denied. Nothing was checked; retry when it is reachable."""

EXIT_CODES_HELP = ("exit codes: 0 ok; 1 failed (verify: missing/extra/corrupt files; publish: refused or "
                   "interrupted); 2 bad input (invalid dataset or version name, version not published, "
                   "unreadable manifest); 3 quality gates failed (publish); 4 cannot reach the store "
                   "(connection, credentials, permission)")
"""The exit codes, as printed in the --help epilog of every store command (see docs/release.md)."""

S3_CLIENT_CONFIG = {"connect_timeout": 10, "read_timeout": 60}
"""botocore client settings of the commands against s3:// stores: a dead endpoint fails in seconds."""
S3_RETRIES = {"max_attempts": 3, "mode": "standard"}
"""botocore retries unless AWS_MAX_ATTEMPTS / AWS_RETRY_MODE set them."""


def add_store_options(p) -> None:
    p.add_argument("--dataset", default="drivetrack-waymo", help="dataset name (folder under the store)")
    p.add_argument("--endpoint-url", default=None,
                   help="S3-compatible endpoint (else AWS_ENDPOINT_URL / AWS config); s3:// stores only")
    p.add_argument("--json", action="store_true", help="print the result as JSON")


def storage_options(args, url: str | None = None) -> dict | None:
    """fsspec options for the store of ``args``: the endpoint, and short timeouts on s3://."""
    url = url if url is not None else getattr(args, "store", "") or ""
    opts: dict = {}
    if getattr(args, "endpoint_url", None):
        opts["client_kwargs"] = {"endpoint_url": args.endpoint_url}
    if str(url).startswith(("s3://", "s3a://")):
        config = dict(S3_CLIENT_CONFIG)
        if not (os.environ.get("AWS_MAX_ATTEMPTS") or os.environ.get("AWS_RETRY_MODE")):
            config["retries"] = dict(S3_RETRIES)
        opts["config_kwargs"] = config
    return opts or None


def print_json(obj) -> None:
    print(json.dumps(obj, indent=1, sort_keys=True, default=str))


def _chain(exc: BaseException):
    seen = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        yield exc
        exc = exc.__cause__ if exc.__cause__ is not None else (
            None if exc.__suppress_context__ else exc.__context__)


def _unreachable_types() -> tuple[type, ...]:
    import asyncio
    import socket

    types: list[type] = [ConnectionError, TimeoutError, asyncio.TimeoutError, socket.gaierror, PermissionError]
    try:
        from botocore import exceptions as bx
        types += [bx.ConnectionError, bx.HTTPClientError, bx.NoCredentialsError, bx.PartialCredentialsError,
                  bx.CredentialRetrievalError, bx.NoRegionError]
    except ImportError:
        pass
    try:
        import aiohttp
        types += [aiohttp.ClientConnectionError]
    except ImportError:
        pass
    return tuple(types)


def unreachable_cause(exc: BaseException) -> BaseException | None:
    """The exception in ``exc``'s chain that says the store could not be reached, or ``None``.

    Release errors that happen to be timeouts (a held lock file) are not "unreachable".
    """
    from drivetrack.release.errors import ReleaseError

    types = _unreachable_types()
    for e in _chain(exc):
        if isinstance(e, types) and not isinstance(e, ReleaseError):
            return e
    return None


def one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= 400 else text[:400] + "..."


def run_store_command(command: str, url: str, body, errors: list[tuple[tuple[type, ...], int]],
                      what: str = "store", after_unreachable: str | None = None,
                      locate=None) -> int:
    """Run ``body()`` and turn its errors into one line on stderr and an exit code.

    Unreachable stores (any connection, DNS, credential or permission error in the exception's
    chain, whatever library raised it) print ``drivetrack COMMAND: cannot reach WHAT URL: CAUSE``
    and return :data:`EXIT_UNREACHABLE` (``locate(cause)`` may return another ``(what, url)``, e.g.
    the source of a publish); other errors are matched against ``errors`` (``(types,
    exit code)`` in order) and print ``drivetrack COMMAND: TYPE: MESSAGE``. Anything else is a bug
    and propagates with its traceback.
    """
    try:
        return int(body() or 0)
    except Exception as e:  # noqa: BLE001 - sorted below, re-raised if unknown
        cause = unreachable_cause(e)
        if cause is not None:
            if locate is not None:
                what, url = locate(cause) or (what, url)
            print(f"drivetrack {command}: cannot reach {what} {url}: {one_line(cause)}", file=sys.stderr)
            if after_unreachable:
                print(f"drivetrack {command}: {after_unreachable}", file=sys.stderr)
            return EXIT_UNREACHABLE
        for types, code in errors:
            if isinstance(e, types):
                print(f"drivetrack {command}: {type(e).__name__}: {e}", file=sys.stderr)
                return code
        raise


def check_dataset_arg(args) -> None:
    """Validate ``--dataset`` (the one dataset-name check, :func:`drivetrack.release.manifest.check_dataset`)."""
    from drivetrack.release.manifest import check_dataset

    if getattr(args, "dataset", None) is not None:
        check_dataset(args.dataset)
