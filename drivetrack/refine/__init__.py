"""Per-object pose refinement: each object's per-frame box pose estimated from its own LiDAR.

Hand labels jitter by centimetres and about a degree from frame to frame; the track stage carries
every point with the labelled boxes, so every jitter moves every track. This module re-estimates
the pose of each object in every frame from the LiDAR itself, with the labels as starting point
and prior, and returns boxes the track stage can use in place of the labels.

Model (one object, T frames, all vectorised; see docs/refinement.md):

- State per frame ``s_t = (c_t, psi_t)``: box centre (metres) and heading (radians, yaw about +z)
  in the vehicle frame of frame t, exactly the parametrisation of a ``lidar_box`` label, so a
  refined box is again a label (``box_from_center_heading``) and a zero correction is the label.
  With ``RefineConfig.pitch_roll_sigma_deg`` (the default) the state also holds the box's pitch
  and roll (``Rz(psi) Ry(pitch) Rx(roll)``, 6 DOF), with a prior towards the labels' tilt and a
  motion term on the box's tilt in the world (see docs/refinement.md, "Pitch and roll").
- Body points: a return ``x`` (vehicle frame of its frame t) has body coordinates
  ``q = box_from_vehicle(s_t) x``; a rigid object's body points are fixed, so the body points of
  all frames form one *model* of the object. A return is used when it lies inside the current box
  grown by ``inlier_margin_m`` and at least ``ground_clearance_m`` above the box bottom (ground).
- Data term (point-to-plane ICP against the other frames): each body point is matched to its
  nearest model point *from another frame* (``scipy.spatial.cKDTree``), with the model normal
  from a local PCA; residual ``r = n . (q - m)``, Huber-weighted with a robust (MAD) scale and
  gated by a point-to-point distance that shrinks over the iterations.
- Label prior: ``(s_t - label_t) / sigma_label`` for every frame. It fixes the gauge (a rigid
  re-definition of the box frame shared by all frames leaves the data term unchanged): the box
  frame ends where the labels put it *on average*, and frames with no points keep the label
  where the motion model has nothing better.
- Motion model: constant velocity and yaw rate in the world frame, i.e. the second divided
  difference of the world centre (``world_from_vehicle_t c_t``) and of the world heading, divided
  by ``accel_sigma_mps2`` (``vertical_accel_sigma_mps2`` for world z) / ``yaw_accel_sigma_radps2``; frames with few points borrow from their
  neighbours.
- All three terms are solved jointly by Gauss-Newton on the 4T unknowns (sparse normal
  equations, early exits for consistent labels), re-associating correspondences at every iteration.

Fallback to the labels when registration is not trustworthy: too few points (in total or frames
with points), a large final robust residual, a correction beyond ``max_correction_m`` /
``max_correction_deg``, or a non-finite result. Every outcome is reported in
:class:`RefinedPoses` (``reason``, corrections, residuals before and after, points per frame).

Modules: :mod:`.config` (``RefineConfig``, ``RefineReason``), :mod:`.poses` (one object:
``refine_object_poses``, ``RefinedPoses``), :mod:`.scene` (every object of a scene:
``refine_scene_boxes``), :mod:`.select` (returns taking part), :mod:`.terms` (normals,
association, normal equations), :mod:`.motion` (motion model), :mod:`.solver` (SPD solve),
:mod:`.kernel` (the numba kernels of the inner loop).
"""
# the pose helpers live in drivetrack.geometry; re-exported here because docs/refinement.md documents them here
from drivetrack.geometry import center_heading_from_poses, poses_from_center_heading, tilt_from_poses
from drivetrack.refine.config import REFINE_REASONS, RefineConfig, RefineReason
from drivetrack.refine.poses import RefinedPoses, refine_object_poses
from drivetrack.refine.scene import refine_scene_boxes

__all__ = ["RefineConfig", "RefineReason", "RefinedPoses", "refine_object_poses", "refine_scene_boxes",
           "REFINE_REASONS", "poses_from_center_heading", "center_heading_from_poses", "tilt_from_poses"]
