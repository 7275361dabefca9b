"""Regenerate tests/golden/npz_sha256.json: the sha256 of the npz the writers write straight from
ObjectTracks (``drivetrack.tracks.write_object_outputs``) for the shared scene of tests/conftest.py
annotated as tests/test_compact.py's ``exported_before_zbuffer``; the export of the release tables
must reproduce them byte for byte. Run after an intended change of the synthetic scene (or of
what that configuration computes: the normals' orientation, 2026-11-27, tenth session; it keeps the
normals' 12 centred neighbours of before the eleventh and twelfth), first on
the code before it (it must reproduce the committed file), then on the new code:
``.venv/bin/python tests/golden/make_npz_sha256.py /tmp/shared_scene``. (Before the world's
placement this script reproduced the digests the pre-v2 writers had recorded, byte for byte.)"""
import hashlib
import json
import shutil
import sys
import tempfile
from pathlib import Path
ROOT = Path(__file__).resolve().parents[2]


def main(src: str, out_json: str) -> int:
    sys.path.insert(0, str(ROOT))
    from drivetrack.annotate import AnnotateConfig, run_segment_stages
    from drivetrack.synth import SynthConfig, generate_segment, segment_name
    from drivetrack.tracks import TrackConfig, write_object_outputs

    if not Path(src, "ok").exists():
        for i in range(2):
            generate_segment(src, SynthConfig(seed=7, frames=30, preset="small"), i)
        Path(src, "ok").write_text("1")
    config = AnnotateConfig(track=TrackConfig(occluder_tolerance_m=1e9, depth_object_motion=False, normals_from="clip",
                                              label_tilt="linear", own_surface_margin_m=None,
                                              box_face_normals_m=None, normal_neighbours=12,
                                              normal_neighbourhood="centred"))
    gold = tempfile.mkdtemp()
    for i in range(2):
        seg = segment_name(7, i)
        with tempfile.TemporaryDirectory() as tmp:
            r = run_segment_stages(src, "training", seg, tmp, config, keep_tracks=True)
            assert r.status == "done", r.error
            for t in r.tracks:
                if t.rejection is None and t.num_tracks > 0:
                    write_object_outputs(gold, "training", t)
    digests = {p.relative_to(gold).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(Path(gold).rglob("*.npz"))}
    Path(out_json).write_text(json.dumps(digests, indent=1) + "\n")
    print(len(digests))
    shutil.rmtree(gold)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2] if len(sys.argv) > 2 else str(Path(__file__).with_name("npz_sha256.json"))))
