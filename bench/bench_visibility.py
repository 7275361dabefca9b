"""Visibility on the hard synthetic world (issue 15): the paper's depth test against ours, one run.

Generates one hard-world segment (``SynthConfig(world="hard")``: oblique cars 20-70 m away, a car
sliding behind a van, poles and a low sign, pedestrians by cars, cars passing close beside the
ego, a turning car, a crossing cyclist; cameras triggered as the TOP sweep passes them), annotates
it once per entry of :data:`VARIANTS` (the paper's depth-ratio test; with the back-face test of
``drivetrack.visibility``; the default ``occlusion="surface"``, which adds the z-buffer of the other
objects' returns; that with labelled objects' returns moved to the image time in the depth maps;
that which also lets no object's own returns in the depth maps hide its points where the
back-face test can decide; that which also narrows the z-buffer's tolerance to 0.15 m; that
which also closes holes between an occluder's splats in the z-buffer; the default, which also
leaves a depth-map surface inside another labelled object's box to the z-buffer),
each with the default pipeline otherwise
(``drivetrack.annotate.annotate_segment``; only the clip selection is widened: all five cameras, every object type,
``min_frames`` 8 and ``max_camera_distance_m`` 75 so that the far and side-camera cases become
clips at all) and scores the tracks against the exact truth:

- pooled occlusion accuracy (OA) over every (track, frame) whose true pixel is inside the image,
  and per clip (TAP-Vid OA, query mode ``first``, from ``drivetrack.evaluation``);
- the false "visible" rate on back-face point-frames (truth ``facing`` is False: the point's face
  turns away from the camera, so it is hidden by its own box) and on point-frames occluded by
  another object;
- OA by camera-to-point distance (<20 m, 20-40, 40-60, 60+);
- per camera and per moving / static object: median pixel error (truth-visible frames) and AJ.

The figures before any fix (issues 15 and 16) stay in docs/benchmarks.md as measured; this
script writes the comparison block (``bench_visibility_compare``). With ``--rolling-shutter`` the
world's cameras are read out row by row (``SynthConfig(rolling_shutter=True)``, as real logs'
are) and the block ``bench_visibility_rolling`` is written instead; ``--variants`` picks
entries of :data:`VARIANTS` or :data:`EXTRA_VARIANTS` (comma-separated names, default every
:data:`VARIANTS` entry). With ``--car-shape cabin`` every vehicle is a body and a cabin inside its
label box (``SynthConfig(car_shape="cabin")``: real cars are not boxes) and the block
``bench_visibility_cabin`` is written; with ``--pedestrian-shape body`` every pedestrian is two
legs, a torso, two arms and a head inside its label box (``SynthConfig(pedestrian_shape="body")``)
and the block ``bench_visibility_body`` is written; with ``--label-noise M`` the written boxes carry M metres
of centre noise and 1 deg of heading noise per 5 cm (``SynthConfig(box_noise_m=M)``: real labels
are drawn by hand around their returns) and the block ``bench_visibility_noise`` is written; with
``--range-noise M`` every written lidar range carries M metres of noise
(``SynthConfig(range_noise_m=M)``: real returns do) and the block ``bench_visibility_range`` is
written; with ``--box-slack M`` every written box is drawn M metres wider than its object on each
side (``SynthConfig(box_slack_m=M)``: hand-drawn labels are) and the block
``bench_visibility_slack`` is written; ``--label-noise`` with ``--box-slack`` (labels both loose
and noisy, as hand-drawn ones are) writes ``bench_visibility_loose``; ``--real-log`` puts every
real-log effect in one world (rolling shutter, cabin cars, body pedestrians, 5 cm / 1 deg label
noise, 2 cm range noise, unless ``--label-noise`` / ``--range-noise`` say otherwise) and writes
``bench_visibility_reallog``. A variant's
``refine_options`` entry sets ``RefineConfig`` fields (the pose refinement's). Each
block counts the wrong calls by kind (truly visible called hidden, back faces called visible,
hidden by another object called visible).

    .venv/bin/python bench/bench_visibility.py                   # medium preset, 20 frames, seed 7 (~10 min, ~5 GB)
    .venv/bin/python bench/bench_visibility.py --preset small --frames 30 --no-docs   # ~1.5 min
    .venv/bin/python bench/bench_visibility.py --rolling-shutter \
        --variants "depth-ratio (paper),+ normals from the plane through the point,+ the object's own surface,+ roofs the lidar did not sample,+ outlines from the occluders' hulls,\
+ normals on cubes sized to the range noise,+ both sides of the outline band,+ planes through their points,+ footprints of 2 cm,+ normals from the face the ray enters by,+ surfaces snapped along their rays,\
+ pedestrians hide with their recent returns,+ depth look-up grown where the labels jitter (default)"   # ~12 min
    .venv/bin/python bench/bench_visibility.py --car-shape cabin --variants "depth-ratio (paper),\
+ normals among 30 neighbours,+ normals from the plane through the point,+ the object's own surface,+ roofs the lidar did not sample,+ outlines from the occluders' hulls,\
+ normals on cubes sized to the range noise,+ both sides of the outline band,+ planes through their points,+ footprints of 2 cm,+ normals from the face the ray enters by,+ surfaces snapped along their rays,\
+ pedestrians hide with their recent returns,+ depth look-up grown where the labels jitter (default)"   # ~12 min
    .venv/bin/python bench/bench_visibility.py --pedestrian-shape body --variants "depth-ratio (paper),\
+ normals from the plane through the point,+ the object's own surface,+ roofs the lidar did not sample,+ outlines from the occluders' hulls,\
+ normals on cubes sized to the range noise,+ both sides of the outline band,+ planes through their points,+ footprints of 2 cm,+ normals from the face the ray enters by,+ surfaces snapped along their rays,\
+ pedestrians hide with their recent returns,+ depth look-up grown where the labels jitter (default)"   # ~10 min
    .venv/bin/python bench/bench_visibility.py --label-noise 0.05 --variants "depth-ratio (paper),\
+ normals among 30 neighbours,+ normals from the plane through the point,+ the object's own surface,+ roofs the lidar did not sample,+ outlines from the occluders' hulls,\
+ normals on cubes sized to the range noise,+ both sides of the outline band,+ planes through their points,+ footprints of 2 cm,+ normals from the face the ray enters by,+ surfaces snapped along their rays,\
+ pedestrians hide with their recent returns,+ depth look-up grown where the labels jitter (default)"   # ~12 min
    .venv/bin/python bench/bench_visibility.py --range-noise 0.02 --variants "depth-ratio (paper),\
+ normals among 30 neighbours,+ shifted neighbourhoods,+ normals from the plane through the point,+ the object's own surface,+ roofs the lidar did not sample,+ outlines from the occluders' hulls,\
+ normals on cubes sized to the range noise,+ both sides of the outline band,+ planes through their points,+ footprints of 2 cm,+ normals from the face the ray enters by,+ surfaces snapped along their rays,\
+ pedestrians hide with their recent returns,+ depth look-up grown where the labels jitter (default)"   # ~15 min
    .venv/bin/python bench/bench_visibility.py --box-slack 0.15 --variants "depth-ratio (paper),\
+ normals from the plane through the point,+ the object's own surface,+ roofs the lidar did not sample,+ outlines from the occluders' hulls,\
+ normals on cubes sized to the range noise,+ both sides of the outline band,+ planes through their points,+ footprints of 2 cm,+ normals from the face the ray enters by,+ surfaces snapped along their rays,\
+ pedestrians hide with their recent returns,+ depth look-up grown where the labels jitter (default)"   # ~6 min
    .venv/bin/python bench/bench_visibility.py --box-slack 0.15 --label-noise 0.05 --variants "depth-ratio (paper),\
registration takes the road and neighbours (before),+ normals from the plane through the point,+ the object's own surface,+ roofs the lidar did not sample,+ outlines from the occluders' hulls,\
+ normals on cubes sized to the range noise,+ both sides of the outline band,+ planes through their points,+ footprints of 2 cm,+ normals from the face the ray enters by,+ surfaces snapped along their rays,\
+ pedestrians hide with their recent returns,+ depth look-up grown where the labels jitter (default)"   # ~8 min
    .venv/bin/python bench/bench_visibility.py --real-log --variants "depth-ratio (paper),\
+ footprints of 2 cm,+ normals from the face the ray enters by,+ surfaces snapped along their rays,\
+ pedestrians hide with their recent returns,+ depth look-up grown where the labels jitter (default)"   # ~12 min
    .venv/bin/python -m bench.run visibility
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DOC = ROOT / "docs" / "benchmarks.md"
DOC_START, DOC_END = "<!-- bench_visibility:start -->", "<!-- bench_visibility:end -->"
CAMERAS = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT", "SIDE_LEFT", "SIDE_RIGHT")
DISTANCE_BINS = ((0.0, 20.0, "<20 m"), (20.0, 40.0, "20-40 m"), (40.0, 60.0, "40-60 m"), (60.0, np.inf, "60+ m"))


def _rate(numerator: np.ndarray) -> float:
    return float(numerator.mean()) if numerator.size else float("nan")


def point_frames(tracks, root: str) -> dict[str, np.ndarray]:
    """Every matched (track, frame) of the accepted clips with its truth, prediction and context:
    arrays of equal length ``camera``, ``role``, ``moving``, ``clip``, ``inside``, ``truth_visible``,
    ``pred_visible``, ``facing``, ``distance_m``, ``error_px``."""
    from drivetrack.evaluation import TruthIndex, clip_from_tracks

    index = None
    out: dict[str, list] = {k: [] for k in ("camera", "role", "moving", "clip", "inside", "truth_visible",
                                            "pred_visible", "facing", "distance_m", "error_px")}
    for ci, t in enumerate(tracks):
        clip = clip_from_tracks(t)
        if index is None or index.truth.segment != clip.segment:
            index = TruthIndex.load(root, "training", clip.segment)
        truth = index.truth
        objects, hits = truth.objects, truth.hits
        frames = index.segment_frames(clip.timestamps_micros, clip.where)
        axis = truth.camera_axis(clip.camera)
        hit = index.match(frames[clip.query_frames], clip.lidar_sources, clip.where)
        ok = hit >= 0
        hm = hit[ok]
        px = hits["pixels"][hm[:, None], axis, frames[None, :]].astype(np.float64)          # [M, T, 2]
        inside = np.isfinite(px[..., 0])
        inside[inside] = t.camera_model.inside_image(px[inside])
        k = hits["object_index"][hm]
        # camera centre at each frame's image time, and the body point at that frame
        world_from_camera = objects["world_from_camera_vehicle"][axis][frames] @ t.camera_model.vehicle_from_camera
        box = objects["world_from_box"][k[:, None], frames[None, :]]                          # [M, T, 4, 4]
        point = np.einsum("mtij,mj->mti", box[..., :3, :3], hits["point_box"][hm]) + box[..., :3, 3]
        distance = np.linalg.norm(point - world_from_camera[None, :, :3, 3], axis=-1)
        pred = np.asarray(clip.tracks[ok], np.float64)
        with np.errstate(invalid="ignore"):
            error = np.linalg.norm(pred - px, axis=-1)
        speed = np.linalg.norm(objects["velocity_world"][k], axis=-1).max(axis=1)            # [M]
        shape = inside.shape
        out["camera"].append(np.full(shape, clip.camera))
        out["role"].append(np.broadcast_to(objects["role"][k].astype(str)[:, None], shape))
        out["moving"].append(np.broadcast_to((speed > 0.1)[:, None], shape))
        out["clip"].append(np.full(shape, ci))
        out["inside"].append(inside)
        out["truth_visible"].append(hits["visible"][hm[:, None], axis, frames[None, :]])
        out["pred_visible"].append(np.asarray(clip.visibles[ok], bool))
        out["facing"].append(hits["facing"][hm[:, None], axis, frames[None, :]])
        out["distance_m"].append(distance)
        out["error_px"].append(error)
    return {key: np.concatenate([a.ravel() for a in v]) if v else np.zeros(0) for key, v in out.items()}


def summarise(pf: dict[str, np.ndarray], clips) -> dict:
    """The tables of the module docstring from :func:`point_frames` and ``evaluate_tracks(...).clips``."""
    m = pf["inside"]
    correct = pf["pred_visible"] == pf["truth_visible"]
    back = m & ~pf["facing"]
    other = m & pf["facing"] & ~pf["truth_visible"]
    result = {
        "point_frames": int(m.sum()), "pooled_oa": _rate(correct[m]),
        "back_face_point_frames": int(back.sum()), "back_face_false_visible": _rate(pf["pred_visible"][back]),
        "occluded_by_other_point_frames": int(other.sum()),
        "occluded_by_other_false_visible": _rate(pf["pred_visible"][other]),
        "visible_point_frames": int((m & pf["truth_visible"]).sum()),
        "wrong": int((m & ~correct).sum()),
        "visible_called_hidden": int((m & pf["truth_visible"] & ~pf["pred_visible"]).sum()),
        "back_face_called_visible": int((back & pf["pred_visible"]).sum()),
        "occluded_by_other_called_visible": int((other & pf["pred_visible"]).sum()),
        "visible_recall": _rate(pf["pred_visible"][m & pf["truth_visible"]]),
        "by_distance": [], "by_role": [], "by_camera_motion": [],
    }
    # positions: the truly visible point-frames' pixel errors
    errors = pf["error_px"][m & pf["truth_visible"]]
    errors = errors[np.isfinite(errors)]
    result["pixel_error"] = ({"median": float(np.median(errors)), "p90": float(np.percentile(errors, 90)),
                              "within_1px": float(np.mean(errors < 1.0))} if errors.size else
                             {"median": float("nan"), "p90": float("nan"), "within_1px": float("nan")})
    for lo, hi, name in DISTANCE_BINS:
        sel = m & (pf["distance_m"] >= lo) & (pf["distance_m"] < hi)
        result["by_distance"].append({"bin": name, "point_frames": int(sel.sum()), "oa": _rate(correct[sel]),
                                      "back_face_false_visible": _rate(pf["pred_visible"][sel & ~pf["facing"]])})
    for role in sorted(set(pf["role"][m])):
        sel = m & (pf["role"] == role)
        result["by_role"].append({"role": role, "point_frames": int(sel.sum()), "oa": _rate(correct[sel]),
                                  "back_face_false_visible": _rate(pf["pred_visible"][sel & ~pf["facing"]])})
    first = clips[clips["query_mode"] == "first"]
    for cam in CAMERAS:
        for moving in (True, False):
            sel = m & (pf["camera"] == cam) & (pf["moving"] == moving) & pf["truth_visible"]
            errors = pf["error_px"][sel]
            errors = errors[np.isfinite(errors)]
            clip_ids = sorted(set(pf["clip"][m & (pf["camera"] == cam) & (pf["moving"] == moving)].tolist()))
            aj = first.iloc[clip_ids]["average_jaccard"] if clip_ids else first.iloc[[]]["average_jaccard"]
            oa_sel = m & (pf["camera"] == cam) & (pf["moving"] == moving)
            result["by_camera_motion"].append({
                "camera": cam, "objects": "moving" if moving else "static", "clips": len(clip_ids),
                "pixel_error_median": float(np.median(errors)) if errors.size else float("nan"),
                "aj": float(aj.mean()) if len(aj) else float("nan"), "oa": _rate(correct[oa_sel])})
    result["per_clip_oa"] = [
        {"camera": r.camera, "object": r.object_id, "oa": float(r.occlusion_accuracy), "aj": float(r.average_jaccard),
         "tracks": int(r.num_tracks), "frames": int(r.num_frames)} for r in first.itertuples()]
    return result


def _f(x, digits=3):
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else f"{x:.{digits}f}"


#: The z-buffer's tolerance before 2026-11-26 (0.3 m + 2% of the depth).
_OLD_TOLERANCE = {"occluder_tolerance_m": 0.3, "occluder_tolerance_rel": 0.02}

#: The z-buffer without hole filling, and the depth map hiding points behind every surface
#: (before 2026-11-26, fifth session).
_BEFORE_FILL = {"occluder_fill_px": 0, "depth_defers_to_zbuffer": False}

#: Unreliable normals left unreliable (before 2026-11-27, tenth session). The own-box rule's ray
#: test at such points has no switch: the variants with the own-box rule carry it.
_BEFORE_FACES = {"box_face_normals_m": None}

#: The z-buffer at one buffer pixel per image pixel (before 2026-11-27, eleventh session). Each
#: object's holes closed on their own (the same session) has no switch: every variant with the
#: z-buffer carries it.
_BEFORE_SUBPIXELS = {"occluder_subpixels": 1}

#: The normals' 12 neighbours (before 2026-11-27, eleventh session). Their neighbourhoods among
#: each cube's mean instead of its first return (the same session) has no switch: every variant
#: with the back-face test carries it.
_BEFORE_NEIGHBOURS = {"normal_neighbours": 12}
_BEFORE_ELEVENTH = {**_BEFORE_SUBPIXELS, **_BEFORE_NEIGHBOURS}

#: Each cloud point's own neighbourhood (before 2026-11-27, twelfth session). Each tracked point
#: taking its nearest cloud point's normal (the same session) has no switch: every variant with
#: the back-face test carries it.
_BEFORE_SHIFT = {"normal_neighbourhood": "centred"}
_BEFORE_TWELFTH = {**_BEFORE_ELEVENTH, **_BEFORE_SHIFT}

#: Each return where the lidar put it (before 2026-11-28, seventeenth session; a no-op on exact ranges).
_BEFORE_SNAP = {"surface_snap_max_m": None}

#: Visibility variants compared in one run (name -> TrackConfig overrides), over the same segment.
VARIANTS = {
    # the paper's maps too: every return where it was captured
    "depth-ratio (paper)": {"occlusion": "depth-ratio", "depth_object_motion": False},
    # the z-buffer switched off by a tolerance no occluder can exceed: back faces alone
    "depth-ratio + back faces": {"occlusion": "surface", **_BEFORE_SNAP, "occluder_tolerance_m": 1e9, "depth_object_motion": False,
                                 "own_surface_margin_m": None, **_BEFORE_FILL, **_BEFORE_FACES, **_BEFORE_TWELFTH},
    "surface: + z-buffer of other objects": {"depth_object_motion": False, **_BEFORE_SNAP, "own_surface_margin_m": None,
                                             **_OLD_TOLERANCE, **_BEFORE_FILL, **_BEFORE_FACES, **_BEFORE_TWELFTH},
    "surface + depth maps at image time": {"own_surface_margin_m": None, **_BEFORE_SNAP, **_OLD_TOLERANCE, **_BEFORE_FILL,
                                           **_BEFORE_FACES, **_BEFORE_TWELFTH},
    # the object's own returns in the depth maps hide none of its points with reliable normals
    "+ own returns left to the back-face test": {**_BEFORE_SNAP, **_OLD_TOLERANCE, **_BEFORE_FILL, **_BEFORE_FACES, **_BEFORE_TWELFTH},
    # the z-buffer's tolerance without the relative term: 0.15 m at any distance
    "+ z-buffer tolerance 0.15 m": {**_BEFORE_SNAP, **_BEFORE_FILL, **_BEFORE_FACES, **_BEFORE_TWELFTH},
    # holes between an occluder's splats closed by 4 px
    "+ z-buffer hole fill 4 px": {**_BEFORE_SNAP, "depth_defers_to_zbuffer": False, **_BEFORE_FACES, **_BEFORE_TWELFTH},
    # a depth-map surface inside another labelled object's box is left to the z-buffer
    "+ depth map defers to the z-buffer": {**_BEFORE_SNAP, **_BEFORE_FACES, **_BEFORE_TWELFTH},
    # unreliable normals on one face of the label box take that face's normal
    "+ label-box faces at unreliable normals": {**_BEFORE_SNAP, **_BEFORE_TWELFTH},
    # the z-buffer at two buffer pixels per image pixel: outlines placed to half a pixel
    "+ z-buffer outlines to half a pixel": {**_BEFORE_SNAP, **_BEFORE_NEIGHBOURS, **_BEFORE_SHIFT},
    # normals among 30 neighbours (each cube's mean): robust to range noise
    "+ normals among 30 neighbours": {**_BEFORE_SNAP, **_BEFORE_SHIFT},
    # each point's normal from the flattest neighbourhood through it: edges kept sharp
    "+ shifted neighbourhoods": {**_BEFORE_SNAP},
    # each return moved along its ray onto its sweep's surface (range noise; exact ranges: as above)
    "+ returns moved onto their surface": {},
}
# the variants above take each tracked point's normal from its nearest cloud point, as they did
_BEFORE_PLANE = {"normal_transfer": "nearest"}
VARIANTS = {name: {**_BEFORE_PLANE, **overrides} for name, overrides in VARIANTS.items()}
# the normal of the cloud point whose plane passes nearest the point: its own face's at an edge
VARIANTS["+ normals from the plane through the point"] = {}
# the variants above leave the object's own surface to the depth map and the back-face test
_BEFORE_OWN = {"self_occlusion": False}
VARIANTS = {name: {**_BEFORE_OWN, **overrides} for name, overrides in VARIANTS.items()}
# the object's own returns in a z-buffer of their own: its cabin hides its deck
VARIANTS["+ the object's own surface"] = {}
# the variants above splat the other objects' returns alone
_BEFORE_ROOF = {"roof_fill": False}
VARIANTS = {name: {**_BEFORE_ROOF, **overrides} for name, overrides in VARIANTS.items()}
# the part of each other object's roof its returns leave unsampled: the level top of their hull
VARIANTS["+ roofs the lidar did not sample"] = {}
# the variants above leave the band along an occluder's outline to the z-buffer's footprint rule
_BEFORE_HULLS = {"occluder_hulls": False}
VARIANTS = {name: {**_BEFORE_HULLS, **overrides} for name, overrides in VARIANTS.items()}
# the rays of that band decided by the other objects' convex hulls
VARIANTS["+ outlines from the occluders' hulls"] = {}
# the variants above fit the back-face normals on the fine cubes whatever the range noise
_BEFORE_NOISE_CUBES = {"normal_noise_cubes": None}
VARIANTS = {name: {**_BEFORE_NOISE_CUBES, **overrides} for name, overrides in VARIANTS.items()}
# under range noise, on cubes sized to the noise (exact ranges: the variant above, bit for bit)
VARIANTS["+ normals on cubes sized to the range noise"] = {}
# the variants above leave a point the footprint rule hides within a buffer pixel of an outline hidden
_BEFORE_EDGES = {"occluder_hull_edges": False}
VARIANTS = {name: {**_BEFORE_EDGES, **overrides} for name, overrides in VARIANTS.items()}
# those points visible when their rays miss every other object's hull as spanned
VARIANTS["+ both sides of the outline band"] = {}
# the variants above give a point near an edge the plane its neighbourhood leaned to, through it or not
_BEFORE_PRECISE = {"normal_precise_m": 0.0}
VARIANTS = {name: {**_BEFORE_PRECISE, **overrides} for name, overrides in VARIANTS.items()}
# a neighbour's plane that passes through the point when the chosen one does not
VARIANTS["+ planes through their points"] = {}
# the variants above splat each occluder return over 5 cm either side and test each point over as much
_BEFORE_FOOTPRINT = {"surfel_radius_m": 0.05}
VARIANTS = {name: {**_BEFORE_FOOTPRINT, **overrides} for name, overrides in VARIANTS.items()}
# 2 cm footprints: the band along an outline left to a footprint's guess narrows
VARIANTS["+ footprints of 2 cm"] = {}
# the variants above give a noisy return the normal of the plane passing nearest it, the noise's choice
_BEFORE_RAY = {"normal_transfer": "plane"}
VARIANTS = {name: {**_BEFORE_RAY, **overrides} for name, overrides in VARIANTS.items()}
# under range noise the face its lidar ray enters by (exact ranges: the variant above, bit for bit)
VARIANTS["+ normals from the face the ray enters by"] = {}
# the variants above draw each object's surface (splats, solid part, hull) from its returns as measured
_BEFORE_SNAP = {"surface_snap_segment": False}
VARIANTS = {name: {**_BEFORE_SNAP, **overrides} for name, overrides in VARIANTS.items()}
# under range noise those returns moved along their rays onto the surface (exact ranges: bit for bit)
VARIANTS["+ surfaces snapped along their rays"] = {}
# the variants above draw a pedestrian in every image from its whole segment's surface
_BEFORE_RECENT = {"occluder_recent_types": ()}
VARIANTS = {name: {**_BEFORE_RECENT, **overrides} for name, overrides in VARIANTS.items()}
# a noisy pedestrian within 15 m hides with its returns of the 3 frames either side of the image
VARIANTS["+ pedestrians hide with their recent returns"] = {}
# the variants above look the depth map up at the max-of-4 pixels alone
_BEFORE_LOOKUP = {"depth_lookup_px": 0}
VARIANTS = {name: {**_BEFORE_LOOKUP, **overrides} for name, overrides in VARIANTS.items()}
# where the labels jitter (1 cm or more, their centres frame to frame), a pixel round them too:
# exact labels keep the max-of-4 (every exact-label block's default column is unchanged)
VARIANTS["+ depth look-up grown where the labels jitter (default)"] = {}
#: ``--real-log``'s label noise (metres, sigma per axis; 1 deg of heading per 5 cm) and range
#: noise (metres, sigma), unless given.
REAL_LOG_LABEL_NOISE_M = 0.05
REAL_LOG_RANGE_NOISE_M = 0.02
#: Variants run only when named in ``--variants``: the default with one rule switched off.
EXTRA_VARIANTS = {
    "own-box rule without a gap limit (before)": {"own_surface_max_gap_m": None},
    "default without the own-box rule": {"own_surface_margin_m": None},
    # the registration takes every return in the grown label box: the road under a label drawn
    # wider than its object, a neighbour's side (``refine_options``: RefineConfig fields)
    "registration takes the road and neighbours (before)": {"refine_options": {"ground_ring": False,
                                                                               "exclusive_returns": False}},
}
COMPARE_START, COMPARE_END = "<!-- bench_visibility_compare:start -->", "<!-- bench_visibility_compare:end -->"
ROLLING_START, ROLLING_END = "<!-- bench_visibility_rolling:start -->", "<!-- bench_visibility_rolling:end -->"
CABIN_START, CABIN_END = "<!-- bench_visibility_cabin:start -->", "<!-- bench_visibility_cabin:end -->"
NOISE_START, NOISE_END = "<!-- bench_visibility_noise:start -->", "<!-- bench_visibility_noise:end -->"
RANGE_START, RANGE_END = "<!-- bench_visibility_range:start -->", "<!-- bench_visibility_range:end -->"
SLACK_START, SLACK_END = "<!-- bench_visibility_slack:start -->", "<!-- bench_visibility_slack:end -->"
LOOSE_START, LOOSE_END = "<!-- bench_visibility_loose:start -->", "<!-- bench_visibility_loose:end -->"
BODY_START, BODY_END = "<!-- bench_visibility_body:start -->", "<!-- bench_visibility_body:end -->"
REALLOG_START, REALLOG_END = "<!-- bench_visibility_reallog:start -->", "<!-- bench_visibility_reallog:end -->"


def compare_markdown(results: dict[str, dict], setup: dict, machine: str) -> str:
    """The comparison block: one column per variant, the same segment and truth."""
    names = list(results)
    rolling = setup.get("rolling_shutter", False)
    cabin = setup.get("car_shape", "box") == "cabin"
    body = setup.get("pedestrian_shape", "box") == "body"
    noise = float(setup.get("label_noise_m", 0.0))
    range_noise = float(setup.get("range_noise_m", 0.0))
    slack = float(setup.get("box_slack_m", 0.0))
    if setup.get("real_log"):
        return _markdown(results, setup, machine, names,
                         "## Visibility on the hard world with every real-log effect at once",
                         "the hard world of the block above with rolling-shutter cameras, cabin-shaped cars, "
                         "pedestrians with legs and arms, written boxes' centres moved by "
                         f"{noise * 100:g} cm (sigma, per axis) and their headings by {noise / 0.05:g} deg, and "
                         f"{range_noise * 100:g} cm of noise on every lidar range (`SynthConfig(world=\"hard\", "
                         "rolling_shutter=True, car_shape=\"cabin\", pedestrian_shape=\"body\", "
                         f"box_noise_m={noise:g}, range_noise_m={range_noise:g})`), same scoring: preset ",
                         " --real-log" + (f" --label-noise {noise:g}" if noise != REAL_LOG_LABEL_NOISE_M else "")
                         + (f" --range-noise {range_noise:g}" if range_noise != REAL_LOG_RANGE_NOISE_M else ""))
    title = ("## Visibility on the hard world with labels {:g} cm wide of their objects and {:g} cm label noise"
             .format(slack * 100, noise * 100) if slack and noise
             else "## Visibility on the hard world read out by a rolling shutter" if rolling
             else "## Visibility on the hard world with cabin-shaped cars" if cabin
             else "## Visibility on the hard world with pedestrians that have legs and arms" if body
             else f"## Visibility on the hard world with {noise * 100:g} cm label noise" if noise
             else f"## Visibility on the hard world with {range_noise * 100:g} cm lidar range noise" if range_noise
             else f"## Visibility on the hard world with labels {slack * 100:g} cm wide of their objects" if slack
             else "## Visibility on the hard world: back faces from each object's own surface")
    world = (f"the hard world of the block above with every written box drawn {slack * 100:g} cm wider than its "
             f"object on each side and its centre moved by {noise * 100:g} cm (sigma, per axis), its heading by "
             f"{noise / 0.05:g} deg (`SynthConfig(world=\"hard\", box_slack_m={slack:g}, box_noise_m={noise:g})`), "
             "same scoring: preset " if slack and noise
             else "the hard world of the block above rendered with rolling-shutter cameras "
             "(`SynthConfig(world=\"hard\", rolling_shutter=True)`), same scoring: preset " if rolling
             else "the hard world of the block above with every vehicle a body and a cabin inside its label "
                  "box (`SynthConfig(world=\"hard\", car_shape=\"cabin\")`), same scoring: preset " if cabin
             else "the hard world of the block above with every pedestrian two legs, a torso, two arms and a head "
                  "inside its label box (`SynthConfig(world=\"hard\", pedestrian_shape=\"body\")`), same scoring: "
                  "preset " if body
             else f"the hard world of the block above with its written boxes' centres moved by {noise * 100:g} cm "
                  f"(sigma, per axis) and their headings by {noise / 0.05:g} deg "
                  f"(`SynthConfig(world=\"hard\", box_noise_m={noise:g})`), same scoring: preset " if noise
             else f"the hard world of the block above with {range_noise * 100:g} cm (sigma) of noise on every written lidar "
                  f"range (`SynthConfig(world=\"hard\", range_noise_m={range_noise:g})`), same scoring: preset "
             if range_noise
             else f"the hard world of the block above with every written box drawn {slack * 100:g} cm wider than "
                  f"its object on each side (`SynthConfig(world=\"hard\", box_slack_m={slack:g})`), same scoring: "
                  "preset " if slack
             else "same segment and scoring as the block above: preset ")
    options = ((" --rolling-shutter" if rolling else "") + (" --car-shape cabin" if cabin else "")
               + (" --pedestrian-shape body" if body else "")
               + (f" --label-noise {noise:g}" if noise else "") + (f" --range-noise {range_noise:g}" if range_noise else "")
               + (f" --box-slack {slack:g}" if slack else ""))
    return _markdown(results, setup, machine, names, title, world, options)


def _markdown(results: dict[str, dict], setup: dict, machine: str, names: list[str], title: str, world: str,
              options: str) -> str:
    """:func:`compare_markdown`'s block under ``title``, the world described by ``world`` and made by
    the command line ``options``."""
    lines = [title, "",
             f"`bench/bench_visibility.py{options}` ({world}"
             f"`{setup['preset']}`, {setup['frames']} frames, seed {setup['seed']}, five cameras, every object "
             f"type, `min_frames` 8, `max_camera_distance_m` 75), annotated once per variant in one run. "
             f"Annotation wall time per variant: "
             + ", ".join(f"{n} {setup['annotate_s'][n]:.0f} s" for n in names) + f". Machine: {machine}.", "",
             "| measure | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    # the cost (issue 15: track stage plus visibility against track stage plus depth completion);
    # the visibility tests run inside the track stage
    stages = setup.get("stage_s", {})
    if stages:
        lines.append("| depth + track stages s | " + " | ".join(
            _f(stages[n].get("depth", float("nan")) + stages[n].get("tracks", float("nan")), 1) for n in names) + " |")

    def row(label, get, digits=3):
        lines.append(f"| {label} | " + " | ".join(_f(get(results[n]), digits) for n in names) + " |")

    row("pooled OA", lambda r: r["pooled_oa"], 4)
    lines.append("| wrong calls: visible called hidden / back faces called visible / hidden by another called "
                 "visible | " + " | ".join(
                     f"{results[n]['wrong']:,}: {results[n]['visible_called_hidden']:,} / "
                     f"{results[n]['back_face_called_visible']:,} / {results[n]['occluded_by_other_called_visible']:,}"
                     if "wrong" in results[n] else "-" for n in names) + " |")
    row("back-face point-frames called visible", lambda r: r["back_face_false_visible"])
    row("point-frames occluded by another object called visible", lambda r: r["occluded_by_other_false_visible"])
    row("truly visible point-frames called visible", lambda r: r["visible_recall"], 4)
    for i, (_, _, label) in enumerate(DISTANCE_BINS):
        row(f"OA {label}", lambda r, i=i: r["by_distance"][i]["oa"], 4)
        row(f"back faces called visible {label}", lambda r, i=i: r["by_distance"][i]["back_face_false_visible"])
    row("pixel error of truly visible point-frames: median px", lambda r: r["pixel_error"]["median"])
    row("... 90th percentile px", lambda r: r["pixel_error"]["p90"])
    row("... within 1 px", lambda r: r["pixel_error"]["within_1px"], 4)
    for i, d in enumerate(results[names[0]]["by_camera_motion"]):
        row(f"AJ {d['camera']} {d['objects']}", lambda r, i=i: r["by_camera_motion"][i]["aj"])
    for i, d in enumerate(results[names[0]]["by_camera_motion"]):
        row(f"median px error {d['camera']} {d['objects']}",
            lambda r, i=i: r["by_camera_motion"][i]["pixel_error_median"])
    lines += ["", "OA per clip (query mode `first`):", "", "| camera | object | " + " | ".join(names) + " |",
              "|---|---|" + "---|" * len(names)]
    per = {n: {(c["camera"], c["object"]): c for c in results[n]["per_clip_oa"]} for n in names}
    for key, c in per[names[0]].items():
        lines.append(f"| {c['camera']} | `{c['object'][:8]}` ({c['role']}) | "
                     + " | ".join(_f(per[n].get(key, {}).get("oa")) for n in names) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    from bench.run import add_hard_world_arguments, machine_description, replace_doc_block
    from drivetrack.annotate import AnnotateConfig, annotate_segment
    from drivetrack.evaluation import evaluate_tracks
    from drivetrack.synth import SynthConfig, generate_segment, load_ground_truth
    from drivetrack.tracks import TrackConfig

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_hard_world_arguments(ap)
    ap.add_argument("--rolling-shutter", action="store_true",
                    help="cameras read out row by row (writes the bench_visibility_rolling block)")
    ap.add_argument("--car-shape", choices=["box", "cabin"], default="box",
                    help="cabin: every vehicle a body and a cabin inside its label box (writes the "
                         "bench_visibility_cabin block)")
    ap.add_argument("--pedestrian-shape", choices=["box", "body"], default="box",
                    help="body: every pedestrian two legs, a torso, two arms and a head inside its label box "
                         "(writes the bench_visibility_body block)")
    ap.add_argument("--label-noise", type=float, default=0.0, metavar="M",
                    help="sigma (metres, per axis) of the noise on the written boxes' centres, with 1 deg of "
                         "heading noise per 5 cm (SynthConfig.box_noise_m; writes the bench_visibility_noise block)")
    ap.add_argument("--range-noise", type=float, default=0.0, metavar="M",
                    help="sigma (metres) of the noise on every written lidar range (SynthConfig.range_noise_m; "
                         "writes the bench_visibility_range block)")
    ap.add_argument("--box-slack", type=float, default=0.0, metavar="M",
                    help="every written box drawn this much (metres) wider than its object on each side "
                         "(SynthConfig.box_slack_m; writes the bench_visibility_slack block)")
    ap.add_argument("--real-log", action="store_true",
                    help="every real-log effect at once: rolling shutter, cabin cars, body pedestrians, "
                         f"{REAL_LOG_LABEL_NOISE_M * 100:g} cm label noise and {REAL_LOG_RANGE_NOISE_M * 100:g} cm "
                         "range noise (--label-noise / --range-noise change those; writes the "
                         "bench_visibility_reallog block)")
    ap.add_argument("--variants", default=None,
                    help="comma-separated names of VARIANTS (or EXTRA_VARIANTS) to run (default: VARIANTS)")
    args = ap.parse_args(argv if argv is not None else [])
    real_log = args.real_log
    if real_log:
        if args.rolling_shutter or args.car_shape != "box" or args.pedestrian_shape != "box" or args.box_slack:
            ap.error("--real-log sets --rolling-shutter, --car-shape cabin and --pedestrian-shape body itself "
                     "and takes no --box-slack; only --label-noise and --range-noise change it")
        args.rolling_shutter, args.car_shape, args.pedestrian_shape = True, "cabin", "body"
        args.label_noise = args.label_noise or REAL_LOG_LABEL_NOISE_M
        args.range_noise = args.range_noise or REAL_LOG_RANGE_NOISE_M
    loose = args.label_noise > 0 and args.box_slack > 0      # the one pair allowed: its own block
    if sum((args.rolling_shutter, args.car_shape == "cabin", args.pedestrian_shape == "body", args.label_noise > 0,
            args.range_noise > 0, args.box_slack > 0)) > 1 + loose and not real_log:
        ap.error("--rolling-shutter, --car-shape cabin, --pedestrian-shape body, --label-noise, --range-noise and "
                 "--box-slack: one at a time "
                 "(one block each), or --label-noise with --box-slack (the bench_visibility_loose block)")
    if not 0 <= args.box_slack <= 0.5:
        ap.error(f"--box-slack must be in [0, 0.5] metres, got {args.box_slack}")
    if args.label_noise < 0:
        ap.error(f"--label-noise must be >= 0 metres, got {args.label_noise}")
    if not 0 <= args.range_noise <= 0.5:
        ap.error(f"--range-noise must be in [0, 0.5] metres, got {args.range_noise}")
    variants = VARIANTS
    if args.variants:
        names = [v.strip() for v in args.variants.split(",") if v.strip()]
        known = {**VARIANTS, **EXTRA_VARIANTS}
        unknown = [v for v in names if v not in known]
        if unknown:
            ap.error(f"--variants: unknown {unknown}; known: {list(known)}")
        variants = {v: known[v] for v in names}
    results, annotate_s, stage_s = {}, {}, {}
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        seg = generate_segment(f"{tmp}/src", SynthConfig(seed=args.seed, frames=args.frames, preset=args.preset,
                                                         cameras=CAMERAS, world="hard",
                                                         rolling_shutter=args.rolling_shutter,
                                                         car_shape=args.car_shape,
                                                         pedestrian_shape=args.pedestrian_shape,
                                                         box_noise_m=args.label_noise,
                                                         range_noise_m=args.range_noise, box_slack_m=args.box_slack),
                               0, workers=args.workers)["segment"]
        generate_s = time.perf_counter() - start
        objects = load_ground_truth(f"{tmp}/src", "training", seg).objects
        role_of = dict(zip(objects["object_id"].astype(str), objects["role"].astype(str)))
        for k, (name, overrides) in enumerate(variants.items()):
            overrides = dict(overrides)
            refine_options = overrides.pop("refine_options", {})
            config = AnnotateConfig(track=TrackConfig(
                cameras=CAMERAS, object_types=("VEHICLE", "PEDESTRIAN", "CYCLIST", "SIGN"), min_frames=8,
                max_camera_distance_m=75.0, **overrides), refine_options=refine_options)
            start = time.perf_counter()
            result = annotate_segment(f"{tmp}/src", "training", seg, f"{tmp}/out{k}", config, keep_tracks=True)
            if result.status != "done":
                raise RuntimeError(f"annotation of {seg} failed at {result.stage}: {result.error}")
            annotate_s[name] = time.perf_counter() - start
            stage_s[name] = {str(k2): float(v) for k2, v in result.timings_s.items()}
            tracks = [t for t in result.tracks if t.rejection is None and t.num_tracks > 0]
            clips = evaluate_tracks(tracks, f"{tmp}/src").clips
            summary = summarise(point_frames(tracks, f"{tmp}/src"), clips)
            for c in summary["per_clip_oa"]:
                c["role"] = role_of[c["object"]]
            results[name] = summary
            print(name, json.dumps({k2: v for k2, v in summary.items() if k2 not in ("per_clip_oa", "by_role")}))
    setup = {"preset": args.preset, "frames": args.frames, "seed": args.seed, "generate_s": generate_s,
             "annotate_s": annotate_s, "stage_s": stage_s, "rolling_shutter": args.rolling_shutter,
             "car_shape": args.car_shape, "pedestrian_shape": args.pedestrian_shape, "label_noise_m": args.label_noise, "range_noise_m": args.range_noise,
             "box_slack_m": args.box_slack, "real_log": real_log}
    if args.json:
        Path(args.json).write_text(json.dumps({"setup": setup, "results": results}, indent=1))
    markdown = compare_markdown(results, setup, machine_description())
    print(markdown)
    if not args.no_docs:
        start, end = ((REALLOG_START, REALLOG_END) if real_log else (LOOSE_START, LOOSE_END) if loose else (ROLLING_START, ROLLING_END) if args.rolling_shutter else (CABIN_START, CABIN_END)
                      if args.car_shape == "cabin" else (BODY_START, BODY_END) if args.pedestrian_shape == "body"
                      else (NOISE_START, NOISE_END) if args.label_noise
                      else (RANGE_START, RANGE_END) if args.range_noise
                      else (SLACK_START, SLACK_END) if args.box_slack else (COMPARE_START, COMPARE_END))
        replace_doc_block(DOC, start, end, f"{start}\n{markdown}{end}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
