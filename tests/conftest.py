"""Session-wide fixtures shared by the test modules.

Generating a synthetic segment costs tens of CPU-seconds, so each test process makes ONE small
source (two segments, 30 frames) and ONE annotation of it, and every module that only reads them
uses these fixtures instead of generating its own (``make test`` shares the test files among a few
processes, pytest-xdist's ``--dist loadfile``: each builds these once, and a module's own fixtures
are built once, in the one process that runs the whole file). Modules that need a special scene (box noise, a
corrupted file) still make their own, as small as they can.
"""
from __future__ import annotations

import atexit
import os
import shutil
import tempfile

import pytest

os.environ.setdefault("DO_NOT_TRACK", "1")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

# The tests' own Prefect: a fresh PREFECT_HOME (database, results, caches) per test session, set
# before anything imports prefect, and no inherited API URL, so that a `make release` or a
# Prefect server of the same checkout (.prefect/) is never shared with the tests.
_PREFECT_HOME = tempfile.mkdtemp(prefix="drivetrack-test-prefect-")
os.environ["PREFECT_HOME"] = _PREFECT_HOME
for _var in ("PREFECT_API_URL", "PREFECT_API_KEY", "PREFECT_PROFILES_PATH"):
    os.environ.pop(_var, None)
atexit.register(shutil.rmtree, _PREFECT_HOME, ignore_errors=True)

SYNTH_SEED = 7
SYNTH_FRAMES = 30
SYNTH_SEGMENTS = 2


@pytest.fixture(scope="session")
def synth_source(tmp_path_factory) -> str:
    """Root of a small synthetic Waymo v2 source: split ``training``, two segments, 30 frames,
    exact ground truth beside it (see docs/synthetic.md)."""
    from drivetrack.synth import SynthConfig, generate_segment

    root = tmp_path_factory.mktemp("synth_source")
    config = SynthConfig(seed=SYNTH_SEED, frames=SYNTH_FRAMES, preset="small")
    for index in range(SYNTH_SEGMENTS):
        generate_segment(str(root), config, index)
    return str(root)


@pytest.fixture(scope="session")
def synth_segments(synth_source) -> list[str]:
    from drivetrack.synth import segment_name

    return [segment_name(SYNTH_SEED, i) for i in range(SYNTH_SEGMENTS)]


@pytest.fixture(scope="session")
def annotated_output(synth_source, synth_segments, tmp_path_factory) -> str:
    """An annotation output folder of ``synth_source`` (default configuration)."""
    from drivetrack.annotate import AnnotateConfig, annotate

    out = tmp_path_factory.mktemp("annotated")
    # two threads whatever the machine: test_staged_api_matches_one_call compares with one
    results = annotate(synth_source, "training", synth_segments, str(out), AnnotateConfig(), threads=2)
    failed = [r for r in results if r.status != "done"]
    assert not failed, [(r.segment, r.error) for r in failed]
    return str(out)


@pytest.fixture(scope="session")
def exported_output(annotated_output, tmp_path_factory) -> str:
    """``annotated_output``'s clips exported as npz (``drivetrack export``, both formats): the
    DriveTrack files under ``tracks/{split}/``, the TAPVid-3D files under ``tapvid3d/{split}/``."""
    from drivetrack.compact.export import FORMATS, export_clips

    out = tmp_path_factory.mktemp("exported")
    export_clips(annotated_output, list(FORMATS), str(out))
    return str(out)
