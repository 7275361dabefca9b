"""Synthetic source -> annotate -> gates -> publish -> verify, through the commands users run.

Issue 5's "must show": on a synthetic release the gates pass and their report is in the release;
with box noise beyond tolerance the release is blocked with a report that names the speed-error
expectation and the objects.
"""
from __future__ import annotations

import json
import shutil
import subprocess

import pandas as pd
import pytest

from drivetrack.cli import main


def test_good_release_passes_gates_and_verifies(annotated_output, tmp_path, capsys):
    out = tmp_path / "out"
    shutil.copytree(annotated_output, out)
    store = tmp_path / "store"
    assert main(["gates", str(out)]) == 0
    assert json.loads((out / "validation" / "gates.json").read_text())["success"] is True
    assert main(["publish", str(out), "--store", str(store), "--version", "0.1.0"]) == 0
    release = store / "drivetrack-waymo" / "0.1.0"
    assert (release / "validation" / "gates.json").exists()
    assert (release / "validation" / "report.html").exists()
    manifest = json.loads((release / "manifest.json").read_text())
    assert manifest["gates"]["success"] is True if "gates" in manifest else True
    card = (release / "README.md").read_text()
    assert card.startswith("---\n") and "gate" in card.lower()
    assert main(["verify", str(store), "--version", "0.1.0"]) == 0
    subprocess.run(["sha256sum", "--quiet", "-c", "SHA256SUMS"], cwd=release, check=True)
    # the clips are in the release as clips/{split}/ and frames/{split}/ tables, the card's configs
    # point at them, and the manifest counts the clip rows
    import pyarrow.parquet as pq

    tables = list((release / "clips" / "training").glob("*.parquet"))
    assert tables and list((release / "frames" / "training").glob("*.parquet"))
    assert "clips/training/*.parquet" in card and "frames/training/*.parquet" in card
    assert not list(release.rglob("*.npz"))
    assert manifest["counts"]["splits"]["training"]["clips"] == sum(pq.read_metadata(t).num_rows for t in tables)
    capsys.readouterr()


@pytest.fixture(scope="module")
def noisy_output(tmp_path_factory):
    """One segment whose written box labels carry 0.3 m / 6 degree noise (truth unchanged)."""
    from drivetrack.annotate import AnnotateConfig, annotate
    from drivetrack.synth import SynthConfig, generate_segment, segment_name

    root = tmp_path_factory.mktemp("noisy_source")
    generate_segment(str(root), SynthConfig(seed=11, frames=30, preset="small", box_noise_m=0.3), 0)
    out = tmp_path_factory.mktemp("noisy_out")
    results = annotate(str(root), "training", [segment_name(11, 0)], str(out), AnnotateConfig())
    assert results[0].status == "done", results[0].error
    return out


def test_noisy_labels_block_the_release(noisy_output, tmp_path, capsys):
    store = tmp_path / "store"
    code = main(["publish", str(noisy_output), "--store", str(store), "--version", "0.2.0"])
    assert code == 3, "a failed gate must block the publish"
    assert not (store / "drivetrack-waymo" / "0.2.0" / "manifest.json").exists()
    report = json.loads((noisy_output / "validation" / "gates.json").read_text())
    assert report["success"] is False
    failed = {r["gate"] if "gate" in r else r.get("id"): r for r in report["results"] if not r["success"]}
    speed = [name for name in failed if "speed_err" in str(name)]
    assert speed, f"a speed-error expectation must fail, failed: {sorted(map(str, failed))}"
    objects = pd.read_parquet(noisy_output / "stats" / "objects.parquet")
    named = json.dumps([failed[n] for n in speed])
    assert any(str(o) in named for o in objects["object_id"]), "the report names the failing objects"
    err = capsys.readouterr()
    assert "speed_err" in (err.out + err.err)
    # Publishing anyway needs an explicit reason, recorded in the manifest and the card.
    assert main(["publish", str(noisy_output), "--store", str(store), "--version", "0.2.0",
                 "--accept-failed-gates", "label-noise study"]) == 0
    release = store / "drivetrack-waymo" / "0.2.0"
    assert "label-noise study" in (release / "manifest.json").read_text()
    assert "label-noise study" in (release / "README.md").read_text()
