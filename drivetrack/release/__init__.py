"""Versioned release store: immutable versions, staged and atomic publish, sha256 manifests,
dataset cards (Hugging Face + Croissant 1.1), verify, diff and gc. See docs/release.md."""
from drivetrack.release.catalog import (DiffReport, GcReport, VerifyReport, diff_versions, gc, list_versions,
                                        read_manifest, verify_release)
from drivetrack.release.errors import (CasConflictError, ConcurrentPublishError, GateBindingError, GatesFailedError,
                                       InvalidSourceError, InvalidVersionError, LockTimeoutError, ManifestError,
                                       PublishConflictError, PublishInterruptedError, ReleaseError,
                                       StagingCheckError, UnsupportedStoreError, VersionExistsError,
                                       VersionNotFoundError)
from drivetrack.release.manifest import SemVer, check_version
from drivetrack.release.publish import DEFAULT_DATASET, PublishResult, check_gate_report, publish_release
from drivetrack.release.store import Store, open_store

__all__ = [
    "CasConflictError", "ConcurrentPublishError", "DEFAULT_DATASET", "DiffReport", "GateBindingError",
    "GatesFailedError", "GcReport",
    "InvalidSourceError", "InvalidVersionError", "LockTimeoutError", "ManifestError", "PublishConflictError",
    "PublishInterruptedError", "PublishResult", "ReleaseError", "SemVer", "StagingCheckError", "Store",
    "UnsupportedStoreError", "VerifyReport", "VersionExistsError", "VersionNotFoundError", "check_gate_report",
    "check_version", "diff_versions", "gc", "list_versions", "open_store", "publish_release", "read_manifest",
    "verify_release",
]
