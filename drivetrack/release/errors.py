"""Errors of the release store. Every message says what happened, where, and what to do next."""
from __future__ import annotations

from drivetrack.names import InvalidNameError


class ReleaseError(Exception):
    """Base class of every release-store error."""


class InvalidVersionError(ReleaseError, ValueError):
    """A version string is not a semantic version (https://semver.org, MAJOR.MINOR.PATCH)."""


class InvalidSourceError(ReleaseError, ValueError):
    """The folder to publish cannot be published as it is (empty, reserved or unsafe names, bad run.json)."""


class InvalidDatasetError(InvalidSourceError, InvalidNameError):
    """A dataset name is not allowed (it becomes a folder name; see :mod:`drivetrack.names`)."""


class UnsafeStorePathError(ReleaseError, ValueError):
    """A path given to the store would leave the store's prefix or cannot name an object safely
    (absolute, ``..``/``.``/empty parts, backslashes or control characters)."""


class GatesFailedError(ReleaseError):
    """The quality gates failed and no reason to accept the failure was given; nothing was written."""


class GateBindingError(ReleaseError, ValueError):
    """The gate report cannot vouch for the folder being published: it has no or an edited content
    binding, contradicts itself, or validated other content (the message names the files that
    differ). ``--accept-failed-gates`` does not override this; nothing was published."""


class PublishConflictError(ReleaseError):
    """Base of the errors raised when a publish loses against another publish of the same version."""


class VersionExistsError(PublishConflictError):
    """The version is already published; published versions are never overwritten."""


class ConcurrentPublishError(PublishConflictError):
    """Another publish of the same version holds the version's claim."""


class PublishInterruptedError(ReleaseError):
    """A publish failed after it had started writing; nothing is visible, it can be resumed or cleaned up."""


class StagingCheckError(ReleaseError):
    """Staged objects do not match what was uploaded (size or sha256)."""


class VersionNotFoundError(ReleaseError, LookupError):
    """The version has no committed manifest in the store."""


class ManifestError(ReleaseError, ValueError):
    """A manifest cannot be parsed or its top-level hash does not match its content."""


class CasConflictError(ReleaseError):
    """A compare-and-swap write found a different previous value than expected."""


class LockTimeoutError(ReleaseError, TimeoutError):
    """A local lock file stayed held longer than the timeout (probably left by a killed process)."""


class UnsupportedStoreError(ReleaseError, ValueError):
    """The store URL's protocol has no conditional-write backend."""
