"""Storage credentials by reference: flow and task parameters never carry a secret.

Prefect stores every flow run's parameters and shows them in the UI and the API, and Dask ships
task arguments between processes. So the flows take ``storage_options`` / ``store_options``
(fsspec keyword arguments) that hold only non-secret settings (``endpoint_url``, ``profile``,
``anon``, ``client_kwargs``...) and *references* to secrets::

    {"profile": "waymo-reader"}                              # an AWS profile (~/.aws on the worker)
    {"key": {"env": "AWS_ACCESS_KEY_ID"},                    # the worker's environment variables
     "secret": {"env": "AWS_SECRET_ACCESS_KEY"},
     "client_kwargs": {"endpoint_url": "https://s3.example.org"}}

:func:`resolve_options` replaces each ``{"env": NAME}`` with ``os.environ[NAME]`` inside the
process that opens the storage (the task, on its Dask worker), at use time. Without any option
s3fs, gcsfs and adlfs find the worker's own credentials (environment, profile, instance role).

:func:`check_no_secrets` refuses a parameter that looks like a secret: an option whose name
says key, secret, token, password, credential, signature or authorization with a literal value
instead of a reference, and any URL with a password in it (``s3://user:pass@...``).
:class:`GuardedFlow` runs the check before Prefect creates the flow run, so a refused secret is
never stored.
"""
from __future__ import annotations

import os
import re
from collections.abc import Mapping
from typing import Any

from prefect import Flow

__all__ = ["SecretParameterError", "check_no_secrets", "resolve_options", "is_reference", "GuardedFlow",
           "guarded_flow"]

SECRET_NAME = re.compile(r"(^|[_\-.])(key|secret|token|password|passwd|pwd|credentials?|signature|sas|"
                         r"authorization|auth|cookie|connection[_\-]?string|private)([_\-.]|$)"
                         r"|secret|token|password|passwd|credential|authorization|apikey|accesskey",
                         re.IGNORECASE)
"""Option names that hold secrets (s3fs ``key``/``secret``/``token``, gcsfs ``token``, adlfs
``account_key``/``sas_token``/``connection_string``, ``password``, ``headers.Authorization``)."""

URL_WITH_PASSWORD = re.compile(r"[A-Za-z][A-Za-z0-9+.\-]*://[^/@\s:]*:[^/@\s]+@")
"""A URL whose authority carries ``user:password@``."""

ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


class SecretParameterError(ValueError):
    """A flow or task parameter holds what looks like a secret instead of a reference."""


def is_reference(value: Any) -> bool:
    """``{"env": "NAME"}``: a reference to an environment variable of the process that uses it."""
    return isinstance(value, Mapping) and set(value) == {"env"} and isinstance(value["env"], str) \
        and ENV_NAME.fullmatch(value["env"]) is not None


def check_no_secrets(params: Mapping[str, Any], where: str) -> None:
    """Raise :class:`SecretParameterError` naming the parameter path (never the value) when a
    parameter looks like a secret; see the module docstring for what passes."""
    def walk(value, path: str, name: str | None) -> None:
        if isinstance(value, Mapping):
            if "env" in value and set(value) == {"env"} and not is_reference(value):
                raise SecretParameterError(f"{where}: {path} = {{'env': ...}} must name an environment variable "
                                           f"([A-Za-z_][A-Za-z0-9_]*)")
            if is_reference(value):
                return
            for k, v in value.items():
                walk(v, f"{path}.{k}" if path else str(k), str(k))
            return
        if isinstance(value, (list, tuple)):
            for i, v in enumerate(value):
                walk(v, f"{path}[{i}]", name)
            return
        if value is None or isinstance(value, bool):
            return
        if name is not None and SECRET_NAME.search(name) and not _harmless(name, value):
            raise SecretParameterError(
                f"{where}: {path} looks like a secret (option {name!r}); Prefect stores and shows flow "
                f"parameters, so pass a reference instead: {{'env': 'VARIABLE'}} resolved on the worker, "
                f"a profile name ('profile': 'NAME'), or nothing (the worker's own credentials); "
                f"see docs/orchestration.md")
        if isinstance(value, str) and URL_WITH_PASSWORD.search(value):
            raise SecretParameterError(f"{where}: {path} is a URL with a password in it (user:password@); "
                                       f"give the credentials by reference (docs/orchestration.md)")

    walk(dict(params), "", None)


def _harmless(name: str, value) -> bool:
    """Settings whose names merely contain a secret-like word (``key_prefix``, ``use_token_auth``
    with a flag value are not secrets; numbers never are)."""
    return isinstance(value, (int, float)) or name.lower() in {"profile", "key_prefix", "sse_kms_key_id"}


def resolve_options(options: Mapping[str, Any] | None, where: str = "storage options") -> dict | None:
    """A copy of ``options`` with every ``{"env": NAME}`` replaced by ``os.environ[NAME]``: call it
    in the process that opens the storage, at use time, and never pass the result to Prefect.
    A missing variable raises KeyError naming it and the option (not any value)."""
    if options is None:
        return None

    def res(value, path):
        if is_reference(value):
            name = value["env"]
            if name not in os.environ:
                raise KeyError(f"{where}: {path} refers to the environment variable {name}, which is not set "
                               f"in this process (pid {os.getpid()}); set it on every worker")
            return os.environ[name]
        if isinstance(value, Mapping):
            return {k: res(v, f"{path}.{k}" if path else str(k)) for k, v in value.items()}
        if isinstance(value, list):
            return [res(v, f"{path}[{i}]") for i, v in enumerate(value)]
        return value

    return res(dict(options), "")


class GuardedFlow(Flow):
    """A Prefect flow that checks its parameters with :func:`check_no_secrets` before Prefect
    serialises them into the flow run it creates (so a refused secret is never stored)."""

    def serialize_parameters(self, parameters):
        check_no_secrets(parameters, f"flow {self.name!r} parameters")
        return super().serialize_parameters(parameters)


def guarded_flow(**options):
    """``@guarded_flow(name=...)``: like ``@prefect.flow`` but a :class:`GuardedFlow`."""
    return lambda fn: GuardedFlow(fn=fn, **options)
