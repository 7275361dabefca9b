"""Content keys for resume and caching: a segment's key is the hash of its source files'
checksums, the configuration's fingerprint and the code's fingerprint; a release's fingerprint
is the hash of its segments' keys and outcomes, the gate configuration and the code.

Same key, same outputs: a re-run reuses every segment whose key has a completion record and
recomputes the rest; a scheduled run whose release fingerprint equals the latest published
one's publishes nothing.
"""
from __future__ import annotations

import hashlib
import importlib.util
import json

import fsspec

import drivetrack
from drivetrack.provenance import source_checksums
from drivetrack.storage import is_local
from drivetrack.waymo.schema import COMPONENTS

__all__ = ["OUTPUT_MODULES", "RELEASE_MODULES", "sha256_json", "code_fingerprint", "segment_checksums",
           "segment_key", "release_fingerprint"]

OUTPUT_MODULES = (
    "drivetrack", "drivetrack.annotate", "drivetrack.boxes", "drivetrack.compact", "drivetrack.compact.layout",
    "drivetrack.compact.read", "drivetrack.compact.write", "drivetrack.camera", "drivetrack.camera.kernel",
    "drivetrack.camera.model",
    "drivetrack.camera.rolling_shutter", "drivetrack.depth", "drivetrack.depth.completers",
    "drivetrack.depth.config", "drivetrack.depth.kernel", "drivetrack.depth.lookup", "drivetrack.depth.registry",
    "drivetrack.depth.sparse", "drivetrack.depth.stage", "drivetrack.depth.torch_nearest", "drivetrack.faults",
    "drivetrack.geometry", "drivetrack.names", "drivetrack.numba_compat", "drivetrack.outputs", "drivetrack.parallel",
    "drivetrack.refine", "drivetrack.refine.config", "drivetrack.refine.extent", "drivetrack.refine.kernel",
    "drivetrack.refine.motion",
    "drivetrack.refine.poses", "drivetrack.refine.scene", "drivetrack.refine.select",
    "drivetrack.refine.solver", "drivetrack.refine.static", "drivetrack.refine.terms", "drivetrack.scene", "drivetrack.storage",
    "drivetrack.tracks", "drivetrack.tracks.config", "drivetrack.tracks.consistency",
    "drivetrack.tracks.context", "drivetrack.tracks.core", "drivetrack.tracks.kernel", "drivetrack.tracks.plan",
    "drivetrack.tracks.stats", "drivetrack.tracks.sweep_motion", "drivetrack.tracks.trajectory", "drivetrack.tidy", "drivetrack.tracks.writers",
    "drivetrack.visibility", "drivetrack.visibility.facing", "drivetrack.visibility.kernel", "drivetrack.visibility.zbuffer", "drivetrack.waymo", "drivetrack.waymo.capture_time", "drivetrack.waymo.checks", "drivetrack.waymo.columns",
    "drivetrack.waymo.components", "drivetrack.waymo.kernel", "drivetrack.waymo.lidar", "drivetrack.waymo.reader",
    "drivetrack.waymo.schema", "drivetrack.waymo.writer",
)
"""Modules whose code can change a segment's outputs (clip files, its stats rows): the code part
of a segment's content key. When unsure, a module belongs here (a needless recompute is cheap, a
stale reuse is wrong). tests/test_package.py checks that every module of the package is declared
here or in :data:`RELEASE_MODULES`."""

RELEASE_MODULES = (
    "drivetrack.cli", "drivetrack.commands", "drivetrack.commands._progress",
    "drivetrack.commands._release_common", "drivetrack.commands.annotate", "drivetrack.commands.diff",
    "drivetrack.commands.export", "drivetrack.compact.export",
    "drivetrack.commands.evaluate", "drivetrack.commands.gates", "drivetrack.commands.gc",
    "drivetrack.commands.info", "drivetrack.commands.publish", "drivetrack.commands.show",
    "drivetrack.commands.status", "drivetrack.commands.synth", "drivetrack.commands.verify",
    "drivetrack.commands.versions", "drivetrack.evaluation", "drivetrack.evaluation.clips",
    "drivetrack.evaluation.metrics", "drivetrack.evaluation.predictions", "drivetrack.evaluation.scoring",
    "drivetrack.evaluation.truth", "drivetrack.gates", "drivetrack.gates.binding", "drivetrack.gates.config",
    "drivetrack.gates.report", "drivetrack.gates.run", "drivetrack.gates.suites", "drivetrack.gates.tables",
    "drivetrack.provenance", "drivetrack.release", "drivetrack.release.assemble", "drivetrack.release.cards",
    "drivetrack.release.catalog", "drivetrack.release.contents", "drivetrack.release.errors",
    "drivetrack.release.keys", "drivetrack.release.manifest", "drivetrack.release.pointers", "drivetrack.release.publish",
    "drivetrack.release.status", "drivetrack.release.status_pages", "drivetrack.release.store",
    "drivetrack.release.work", "drivetrack.show", "drivetrack.show.clips", "drivetrack.show.draw",
    "drivetrack.show.errors", "drivetrack.show.previews", "drivetrack.synth", "drivetrack.synth.boxes",
    "drivetrack.synth.config", "drivetrack.synth.generate", "drivetrack.synth.ground_truth",
    "drivetrack.synth.lidar_cast", "drivetrack.synth.preview", "drivetrack.synth.raycast",
    "drivetrack.synth.render", "drivetrack.synth.sensors", "drivetrack.synth.state", "drivetrack.synth.tables",
    "drivetrack.synth.texture", "drivetrack.synth.truth", "drivetrack.synth.world", "drivetrack.waymo.summary",
)
"""Modules that do not change a segment's outputs but do change a release (commands, gates,
release assembly and publishing, previews, evaluation, the synthetic source): they enter only
the release fingerprint."""


def sha256_json(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, separators=(",", ":"), default=str).encode()).hexdigest()


def _module_source(name: str) -> bytes:
    spec = importlib.util.find_spec(name)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        raise LookupError(f"code fingerprint: declared module {name!r} has no Python source (moved or renamed? "
                          f"update OUTPUT_MODULES / RELEASE_MODULES in drivetrack/release/keys.py)")
    with open(spec.origin, "rb") as handle:
        return handle.read()


def code_fingerprint(*, outputs_only: bool = False) -> str:
    """sha256 over the package version and the source of every declared module
    (:data:`OUTPUT_MODULES`, plus :data:`RELEASE_MODULES` unless ``outputs_only``: the segment
    key's code part). Each module enters as the sha256 of its source, in sorted order, so moving
    a module whole keeps the fingerprint; changing any declared module's code changes it."""
    names = OUTPUT_MODULES + (() if outputs_only else RELEASE_MODULES)
    h = hashlib.sha256(f"drivetrack {drivetrack.__version__}\n".encode())
    for digest in sorted(hashlib.sha256(_module_source(name)).hexdigest() for name in names):
        h.update(digest.encode() + b"\n")
    return h.hexdigest()


def segment_checksums(source: str, split: str, segment: str, *, storage_options: dict | None = None,
                      memo: dict | None = None) -> dict[str, str]:
    """Component name -> checksum of ``{source}/{split}/{component}/{segment}.parquet`` for every
    component present (:func:`drivetrack.provenance.source_checksums` with ``store_tags``: local
    files the sha256 of the bytes, memoised on size and mtime in ``memo``; object stores the
    checksum the store reports with the size). Raises FileNotFoundError naming the segment when
    no component file exists."""
    fs, base = fsspec.core.url_to_fs(str(source), **(storage_options or {}))
    base = base.rstrip("/")
    files = {}
    for comp in COMPONENTS:
        path = f"{base}/{split}/{comp}/{segment}.parquet"
        if fs.exists(path):
            files[comp] = path if is_local(fs) else fs.unstrip_protocol(path)
    if not files:
        raise FileNotFoundError(f"segment {segment!r}: no component file under {source}/{split}/*/"
                                f"{segment}.parquet")
    return source_checksums(files, storage_options, store_tags=True, memo=memo)


def segment_key(split: str, segment: str, checksums: dict[str, str], config_fingerprint: str,
                code: str) -> str:
    """The content key of one segment's outputs (hex sha256)."""
    return sha256_json({"split": split, "segment": segment, "source": checksums, "config": config_fingerprint,
                        "code": code})


def release_fingerprint(dataset: str, segments: list[dict], *, config_fingerprint: str, gates: dict | str | None,
                        code: str) -> str:
    """Hash of what a release would contain: every segment's (split, segment, key, state),
    the configuration, the gate configuration and the full code fingerprint."""
    rows = sorted((s["split"], s["segment"], s.get("key"), s.get("state")) for s in segments)
    return sha256_json({"dataset": dataset, "segments": rows, "config": config_fingerprint, "gates": gates,
                        "code": code})
