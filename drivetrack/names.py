"""The one place that decides whether a name may become part of a path.

Every name that ends up in a file or folder name goes through :func:`check_name` before any path is
built from it: dataset names, release versions (see :mod:`drivetrack.release.manifest` for the
semver grammar, checked with a full match too), split names, segment ids, camera names and object
ids read from source data, and the release files a status page links (``release_file``). Patterns are applied with :func:`re.fullmatch`, never ``re.match`` with
``$`` (which lets a trailing newline through), and no name may be ``.``, ``..``, start with a dot or
an underscore (reserved for the store's own ``_staging``/``_txn`` folders), or hold a separator.
"""
from __future__ import annotations

import re

__all__ = ["NAME_KINDS", "InvalidNameError", "check_name", "is_valid_name"]


class InvalidNameError(ValueError):
    """A name that would become part of a path is not allowed; the message names kind, value and rule."""


# kind -> (pattern for re.fullmatch, human description of the rule)
_WORD = r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}"
NAME_KINDS: dict[str, tuple[re.Pattern, str]] = {
    "dataset": (re.compile(_WORD), "letters, digits, '.', '_' and '-', starting with a letter or digit, "
                                   "at most 128 characters"),
    "split": (re.compile(_WORD), "letters, digits, '.', '_' and '-', starting with a letter or digit"),
    "segment": (re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]{0,255}"),
                "letters, digits, '_', '.' and '-', starting with a letter or digit"),
    "camera": (re.compile(r"[A-Z][A-Z0-9_]{0,31}"), "an upper-case camera name such as FRONT or SIDE_LEFT"),
    "object_id": (re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,255}"),
                  "letters, digits, '_', '.' and '-', not starting with '.'"),
    # a file inside a release, as a page links it: relative, no scheme, no '..', no leading '/'
    "release_file": (re.compile(r"[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,255}(?:/[A-Za-z0-9_\-][A-Za-z0-9_.\-]{0,255}){0,15}"),
                     "a relative path inside the release: '/'-separated parts of letters, digits, '_', '.' "
                     "and '-', no part starting with '.'"),
}


def is_valid_name(kind: str, value) -> bool:
    """True when ``value`` is a valid name of ``kind`` (one of :data:`NAME_KINDS`)."""
    try:
        pattern, _ = NAME_KINDS[kind]
    except KeyError:
        raise ValueError(f"unknown name kind {kind!r}; known: {sorted(NAME_KINDS)}") from None
    return (isinstance(value, str) and pattern.fullmatch(value) is not None
            and value not in (".", "..") and ".." not in value.split("/"))


def check_name(kind: str, value, where: str | None = None) -> str:
    """Return ``value`` when it is a valid name of ``kind``; else raise :class:`InvalidNameError`.

    ``where`` (a file, segment or column) is added to the message so that the error says where the
    bad name came from.
    """
    if is_valid_name(kind, value):
        return value
    _, rule = NAME_KINDS[kind]
    at = f" (in {where})" if where else ""
    raise InvalidNameError(f"{kind} name {value!r}{at} is not allowed: use {rule}")
