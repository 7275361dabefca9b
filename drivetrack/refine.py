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
"""
from __future__ import annotations

import time
from dataclasses import asdict, dataclass, fields

import numpy as np

from drivetrack.geometry import box_from_center_heading

__all__ = ["RefineConfig", "RefinedPoses", "refine_object_poses", "refine_scene_boxes",
           "REFINE_REASONS", "poses_from_center_heading", "center_heading_from_poses", "tilt_from_poses"]

#: ``RefinedPoses.reason`` values. ``refined``: refined poses returned; ``disabled``: refinement
#: off by configuration; ``labels_consistent``: the labels are already as consistent with the
#: LiDAR as the refined poses (within ``min_improvement``), so they are kept unchanged; the others
#: are fallbacks to the labels (``used_fallback``).
REFINE_REASONS = ("refined", "disabled", "labels_consistent", "too_few_points", "large_residual", "large_correction",
                  "not_finite")


@dataclass(frozen=True)
class RefineConfig:
    """Every knob of the pose refinement (defaults tuned on synthetic scenes, see benchmarks).

    Attributes:
        enabled: refine (True) or return the labels unchanged with reason ``disabled``.
        iterations: maximum Gauss-Newton iterations (each re-associates correspondences).
        candidate_margin_m: (``refine_scene_boxes``) candidates are the returns inside the label
            box grown by this much.
        inlier_margin_m: a return takes part when inside the *current* box grown by this.
        ground_clearance_m: returns less than this above the current box bottom are ignored.
        max_correspondence_m, min_correspondence_m: point-to-point gate of a correspondence,
            shrinking geometrically from the first to the second over the iterations.
        huber_k: Huber threshold in units of the robust residual scale.
        point_sigma_floor_m: floor of the robust residual scale (LiDAR noise), metres.
        normal_neighbours: model points in the PCA giving each model normal.
        min_planarity: a correspondence's weight is scaled by the planarity of its model
            neighbourhood ((l2 - l1) / l3 of the PCA eigenvalues) over this, capped at 1: points
            on a scan line or an edge, whose normal is undefined, count less or not at all.
        association_neighbours: nearest model points examined to find one from another frame.
        max_points_per_frame: at most this many returns per frame take part (a fixed
            pseudo-random subset, deterministic); bounds the cost on near objects.
        label_sigma_m, label_sigma_deg: the labels' per-frame noise (prior strength).
        accel_sigma_mps2, vertical_accel_sigma_mps2, yaw_accel_sigma_radps2: motion model
            stiffness: horizontal, vertical (world z; roads are smooth and the LiDAR sees little
            of a roof, so z is the least observed direction) and yaw acceleration.
        pitch_roll_sigma_deg: None: 4 degrees of freedom per frame (centre, heading: the labels'
            parametrisation; a refined box is yaw-only like a label). A number: 6 (and pitch,
            roll), with a prior of this sigma towards the labels' tilt (0 for ``lidar_box``
            labels: level in the vehicle frame); refined boxes then carry ``pitch``/``roll``.
        pitch_roll_accel_sigma_radps2: (6 DOF) motion model stiffness of the box's pitch and
            roll in the *world* (the ego's own pitch and roll are taken out with its pose).
        min_points_total, min_frames_with_points, min_points_per_frame: fallback
            ``too_few_points`` unless the labels select at least ``min_points_total`` returns and
            at least ``min_frames_with_points`` frames have ``min_points_per_frame`` returns.
        max_residual_m: fallback ``large_residual`` when the final robust point-to-plane
            residual (1.4826 x median |r|) exceeds this.
        max_correction_m, max_correction_deg: fallback ``large_correction`` beyond these.
        min_improvement: keep the labels (reason ``labels_consistent``) unless the refined robust
            residual is lower than the labels' by more than this fraction.
        early_stop_iteration: after this many iterations keep the labels (``labels_consistent``)
            unless the robust residual has already dropped by ``min_improvement`` below the
            labels' (0: never stop early). It is measured at that iteration's tighter gate, which
            only flatters it, so the stop is conservative: consistent labels cost this many
            iterations instead of all; noisy labels drop their residual within 1-2 iterations.
        tolerance_m, tolerance_deg: stop (at the finest gate) when the RMS over frames of an
            iteration's centre / heading step is below these.
        fit_extent: grow a refined object's box (size and centre, the same body-frame change in
            every frame; never shrunk, bottom kept) so that it holds the registered returns of
            all frames plus ``extent_margin_m``, by at most ``max_extent_growth_m`` per face.
            Relative poses, hence carried tracks, are unchanged; what changes is which returns
            the track stage selects (see docs/refinement.md, "Box extent").
        kernel: ``numba`` (default: k-nearest search, normals and normal equations in the fused
            kernels of ``drivetrack.refine_kernel``) or ``numpy`` (the scipy/numpy reference,
            same results up to floating-point rounding and ties).
    """
    enabled: bool = True
    iterations: int = 10
    candidate_margin_m: float = 0.4
    inlier_margin_m: float = 0.15
    ground_clearance_m: float = 0.2
    max_correspondence_m: float = 0.3
    min_correspondence_m: float = 0.06
    huber_k: float = 2.0
    point_sigma_floor_m: float = 0.005
    normal_neighbours: int = 12
    min_planarity: float = 0.3
    association_neighbours: int = 12
    max_points_per_frame: int = 120
    label_sigma_m: float = 0.05
    label_sigma_deg: float = 1.0
    accel_sigma_mps2: float = 2.0
    vertical_accel_sigma_mps2: float = 0.3
    yaw_accel_sigma_radps2: float = 1.0
    pitch_roll_sigma_deg: float | None = 1.0
    pitch_roll_accel_sigma_radps2: float = 0.1
    min_points_total: int = 60
    min_frames_with_points: int = 3
    min_points_per_frame: int = 10
    max_residual_m: float = 0.05
    max_correction_m: float = 0.5
    max_correction_deg: float = 10.0
    min_improvement: float = 0.15
    early_stop_iteration: int = 2
    tolerance_m: float = 1e-3
    tolerance_deg: float = 0.02
    fit_extent: bool = True
    extent_margin_m: float = 0.02
    max_extent_growth_m: float = 0.1
    kernel: str = "numba"

    def __post_init__(self):
        positive = ("iterations", "max_correspondence_m", "min_correspondence_m", "huber_k",
                    "point_sigma_floor_m", "min_planarity", "label_sigma_m", "label_sigma_deg", "accel_sigma_mps2",
                    "yaw_accel_sigma_radps2", "vertical_accel_sigma_mps2", "pitch_roll_accel_sigma_radps2",
                    "max_residual_m", "max_correction_m",
                    "max_correction_deg", "max_points_per_frame", "tolerance_m", "tolerance_deg")
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"RefineConfig.{name} must be a positive number, got {value!r}")
        for name in ("extent_margin_m", "max_extent_growth_m", "candidate_margin_m", "inlier_margin_m", "min_points_total", "min_points_per_frame",
                     "min_improvement", "early_stop_iteration"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"RefineConfig.{name} must be >= 0, got {value!r}")
        if self.pitch_roll_sigma_deg is not None and not (np.isfinite(self.pitch_roll_sigma_deg)
                                                          and self.pitch_roll_sigma_deg > 0):
            raise ValueError(f"RefineConfig.pitch_roll_sigma_deg must be a positive number or None (4 DOF), "
                             f"got {self.pitch_roll_sigma_deg!r}")
        if self.normal_neighbours < 3:
            raise ValueError(f"RefineConfig.normal_neighbours must be >= 3, got {self.normal_neighbours}")
        if self.association_neighbours < 2:
            raise ValueError(f"RefineConfig.association_neighbours must be >= 2, got {self.association_neighbours}")
        if self.min_frames_with_points < 2:
            raise ValueError(f"RefineConfig.min_frames_with_points must be >= 2 (registration needs another "
                             f"frame), got {self.min_frames_with_points}")
        if self.kernel not in ("numba", "numpy"):
            raise ValueError(f"RefineConfig.kernel must be 'numba' or 'numpy', got {self.kernel!r}")
        if self.min_correspondence_m > self.max_correspondence_m:
            raise ValueError(f"RefineConfig.min_correspondence_m ({self.min_correspondence_m}) exceeds "
                             f"max_correspondence_m ({self.max_correspondence_m})")

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, values: dict) -> "RefineConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise, naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"RefineConfig: unknown keys {unknown}")
        return cls(**values)


@dataclass
class RefinedPoses:
    """Result of :func:`refine_object_poses` for one object over its T frames.

    Attributes:
        vehicle_from_box: float64 [T, 4, 4], refined box poses (the labels on fallback), vehicle
            frame of each frame; rotation ``Rz(heading) Ry(pitch) Rx(roll)`` (yaw-only, like a
            label, with ``RefineConfig.pitch_roll_sigma_deg=None``).
        world_from_box: float64 [T, 4, 4] = ``world_from_vehicle @ vehicle_from_box``.
        center_vehicle: float64 [T, 3] metres and heading: float64 [T] radians in (-pi, pi] of
            the returned boxes (vehicle frame of each frame).
        size: float64 [T, 3] metres, of the returned boxes: the input sizes, grown on refined
            objects with ``RefineConfig.fit_extent``.
        correction_translation_m: float64 [T, 3], returned centre minus label centre (vehicle
            frame), zero on fallback.
        correction_rotation_deg: float64 [T], returned heading minus label heading, wrapped to
            (-180, 180], zero on fallback.
        pitch, roll: float64 [T] radians of the returned boxes (the labels' on fallback: 0 for
            yaw-only labels; 0 with 4 DOF).
        residual_m: robust point-to-plane residual (1.4826 x median |r|, metres) of the refined
            poses; NaN when never computed (too few points, disabled).
        residual_label_m: the same measure at the labels (the labels' own consistency).
        residual_per_frame_m: float64 [T], RMS of the Huber-inlier residuals per frame at the
            refined poses (NaN where a frame has no correspondence).
        num_points: int64 [T], returns taking part in the registration per frame.
        refined: True when refined poses are returned.
        used_fallback: True when refinement ran but the labels are returned.
        reason: one of :data:`REFINE_REASONS`; ``detail``: human-readable numbers behind it.
        iterations: Gauss-Newton iterations run.
        cpu_seconds: process CPU time spent in the call.
    """
    vehicle_from_box: np.ndarray
    world_from_box: np.ndarray
    center_vehicle: np.ndarray
    heading: np.ndarray
    size: np.ndarray
    correction_translation_m: np.ndarray
    correction_rotation_deg: np.ndarray
    residual_m: float
    residual_label_m: float
    residual_per_frame_m: np.ndarray
    num_points: np.ndarray
    refined: bool
    used_fallback: bool
    reason: str
    detail: str = ""
    iterations: int = 0
    cpu_seconds: float = 0.0
    pitch: np.ndarray | None = None
    roll: np.ndarray | None = None

    def summary(self) -> dict:
        """Flat dict for the statistics tables and the gates (one row per object)."""
        translation = np.linalg.norm(self.correction_translation_m, axis=-1)
        rotation = np.abs(self.correction_rotation_deg)
        has = translation.size > 0
        return {
            "refine_reason": self.reason,
            "refine_applied": bool(self.refined),
            "refine_fallback": bool(self.used_fallback),
            "refine_translation_p50_m": float(np.median(translation)) if has else 0.0,
            "refine_translation_max_m": float(translation.max()) if has else 0.0,
            "refine_rotation_p50_deg": float(np.median(rotation)) if has else 0.0,
            "refine_rotation_max_deg": float(rotation.max()) if has else 0.0,
            "refine_tilt_max_deg": float(np.rad2deg(np.max(np.hypot(self.pitch, self.roll))))
            if has and self.pitch is not None else 0.0,
            "refine_residual_m": float(self.residual_m),
            "refine_residual_label_m": float(self.residual_label_m),
            "refine_num_points": int(self.num_points.sum()),
            "refine_frames_without_points": int((self.num_points == 0).sum()),
            "refine_iterations": int(self.iterations),
            "refine_cpu_seconds": float(self.cpu_seconds),
        }


# ----------------------------------------------------------------------------- small helpers

def poses_from_center_heading(center: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """float64 [T, 4, 4] ``vehicle_from_box`` of centres [T, 3] and headings [T] (radians)."""
    return box_from_center_heading(center, heading)


def center_heading_from_poses(vehicle_from_box: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(centre float64 [T, 3], heading float64 [T]) of yaw-dominant box poses [T, 4, 4].

    The heading is the yaw of the box x axis projected on the vehicle xy plane (the convention
    ``lidar_box`` labels use); roll and pitch, if any, are dropped.
    """
    vehicle_from_box = np.asarray(vehicle_from_box, dtype=np.float64)
    return vehicle_from_box[..., :3, 3].copy(), np.arctan2(vehicle_from_box[..., 1, 0], vehicle_from_box[..., 0, 0])


def _wrap(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    return -((-np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi)


def _to_body(vec: np.ndarray, heading: np.ndarray, tilt: np.ndarray | None) -> np.ndarray:
    """float64 [M, 3] ``R^T vec`` for vectors vec [M, 3], R = Rz(heading) Ry(pitch) Rx(roll) per row
    (heading [M], tilt [M, 2] = (pitch, roll) or None: yaw only)."""
    c, s = np.cos(heading), np.sin(heading)
    u = np.stack([c * vec[:, 0] + s * vec[:, 1], -s * vec[:, 0] + c * vec[:, 1], vec[:, 2]], axis=-1)
    if tilt is None:
        return u
    ct, st, cr, sr = np.cos(tilt[:, 0]), np.sin(tilt[:, 0]), np.cos(tilt[:, 1]), np.sin(tilt[:, 1])
    vx, vz = ct * u[:, 0] - st * u[:, 2], st * u[:, 0] + ct * u[:, 2]                 # Ry^T u
    return np.stack([vx, cr * u[:, 1] + sr * vz, -sr * u[:, 1] + cr * vz], axis=-1)   # Rx^T v


def _from_body(vec: np.ndarray, heading: np.ndarray, tilt: np.ndarray | None) -> np.ndarray:
    """float64 [M, 3] ``R vec``: the inverse of :func:`_to_body`."""
    if tilt is not None:
        ct, st, cr, sr = np.cos(tilt[:, 0]), np.sin(tilt[:, 0]), np.cos(tilt[:, 1]), np.sin(tilt[:, 1])
        vy, vz = cr * vec[:, 1] - sr * vec[:, 2], sr * vec[:, 1] + cr * vec[:, 2]     # Rx q
        vec = np.stack([ct * vec[:, 0] + st * vz, vy, -st * vec[:, 0] + ct * vz], axis=-1)  # Ry v
    c, s = np.cos(heading), np.sin(heading)
    return np.stack([c * vec[:, 0] - s * vec[:, 1], s * vec[:, 0] + c * vec[:, 1], vec[:, 2]], axis=-1)


def _body_points(center: np.ndarray, heading: np.ndarray, points: np.ndarray, frame: np.ndarray,
                 tilt: np.ndarray | None = None) -> np.ndarray:
    """float64 [M, 3]: ``box_from_vehicle(s_frame) x`` for points x [M, 3] of frames ``frame``
    (tilt [T, 2] = per-frame (pitch, roll), None: yaw-only boxes)."""
    return _to_body(points - center[frame], heading[frame], None if tilt is None else tilt[frame])


def tilt_from_poses(vehicle_from_box: np.ndarray) -> np.ndarray:
    """float64 [T, 2] (pitch, roll) radians of box poses [T, 4, 4] with rotation
    ``Rz(heading) Ry(pitch) Rx(roll)``; exactly 0 for yaw-only poses."""
    r = np.asarray(vehicle_from_box, dtype=np.float64)[..., :3, :3]
    return np.stack([-np.arcsin(np.clip(r[..., 2, 0], -1.0, 1.0)), np.arctan2(r[..., 2, 1], r[..., 2, 2])], axis=-1)


def _inside(q: np.ndarray, half: np.ndarray, margin: float, clearance: float) -> np.ndarray:
    """bool [M]: body points q [M, 3] inside boxes of half-size half [M, 3] grown by ``margin``,
    at least ``clearance`` above the (ungrown) bottom."""
    inside = np.all(np.abs(q[:, :2]) <= half[:, :2] + margin, axis=-1)
    return inside & (q[:, 2] <= half[:, 2] + margin) & (q[:, 2] >= -half[:, 2] + clearance)


class _Selection:
    """The returns that may take part, ordered by (frame, priority), with per-frame ranks.

    The per-frame cap keeps the ``cap`` returns of lowest priority that are inside the current
    box. Points are held sorted by (frame, priority), so that subset always lies among the first
    few of its frame that are inside: each iteration tests only the first ``screen`` (a small
    multiple of the cap) of every frame and widens to the whole frame only where those hold
    fewer than ``cap`` inside. The result is exactly the cap over all points, at a cost bounded
    by ``screen x T`` instead of the candidate count (tens of thousands on near objects).
    """

    def __init__(self, points: np.ndarray, frame: np.ndarray, priority: np.ndarray, half: np.ndarray,
                 cap: int, t_count: int, kernel: bool = False):
        order = np.lexsort((priority, frame))
        self.points, self.frame = points[order], frame[order]
        self.half_frame = np.ascontiguousarray(half, dtype=np.float64)        # [T, 3]
        self.half = half[self.frame]
        self.cap, self.t_count, self.kernel = cap, t_count, kernel
        counts = np.bincount(self.frame, minlength=t_count)
        self.counts = counts.astype(np.int64)
        self.start = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
        self.rank = np.arange(self.frame.size) - self.start[self.frame]
        self.screen = 3 * cap
        self.screened = np.flatnonzero(self.rank < self.screen)
        self.frame_full = counts > self.screen          # frames with returns beyond the screen

    def select(self, center: np.ndarray, heading: np.ndarray, margin: float, clearance: float,
               tilt: np.ndarray | None = None):
        """(body points float64 [P, 3], frames int64 [P], rows int64 [P] into ``self.points``) of
        the capped returns inside the boxes (center [T, 3], heading [T], tilt [T, 2] or None)
        grown by ``margin``, in (frame, priority) order. With ``kernel``: one pass per frame in
        priority order that stops at the cap (``refine_kernel.select``), the same subset."""
        if self.kernel:
            from drivetrack import refine_kernel

            return refine_kernel.select(self.points, self.start, self.counts, self.half_frame, self.cap,
                                        center, heading, tilt, margin, clearance)
        idx = self.screened
        f = self.frame[idx]
        q = _body_points(center, heading, self.points[idx], f, tilt)
        inside = _inside(q, self.half[idx], margin, clearance)
        short = self.frame_full & (np.bincount(f[inside], minlength=self.t_count) < self.cap)
        if short.any():                                 # widen to whole frames where needed
            more = np.flatnonzero(short[self.frame] & (self.rank >= self.screen))
            q_more = _body_points(center, heading, self.points[more], self.frame[more], tilt)
            in_more = _inside(q_more, self.half[more], margin, clearance)
            idx = np.concatenate([idx[inside], more[in_more]])
            q = np.concatenate([q[inside], q_more[in_more]])
            order = np.argsort(idx, kind="stable")
            idx, q = idx[order], q[order]
        else:
            idx, q = idx[inside], q[inside]
        f = self.frame[idx]
        counts = np.bincount(f, minlength=self.t_count)
        start = np.concatenate([[0], np.cumsum(counts)[:-1]])
        keep = (np.arange(idx.size) - start[f]) < self.cap
        return q[keep], f[keep], idx[keep]


def _normals(model: np.ndarray, neighbours: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals float64 [P, 3] by PCA over neighbour lists int [P, k] into ``model`` [*, 3],
    and the planarity float64 [P] ((l2 - l1) / l3 of the eigenvalues l1 <= l2 <= l3) of each.

    Closed-form eigen-decomposition of the 3x3 covariances (trigonometric solution of the
    characteristic cubic; the normal is the largest cross product of two rows of ``C - l1 I``):
    an order of magnitude cheaper than batched LAPACK on thousands of 3x3 matrices. The sign of
    a normal is arbitrary (residual and Jacobian flip together).
    """
    gathered = model[neighbours]                                           # [P, k, 3]
    mean_point = gathered.mean(axis=1)
    cov = np.matmul(gathered.transpose(0, 2, 1), gathered) / neighbours.shape[1] \
        - mean_point[:, :, None] * mean_point[:, None, :]
    off = cov[:, 0, 1] ** 2 + cov[:, 0, 2] ** 2 + cov[:, 1, 2] ** 2
    mean = np.trace(cov, axis1=1, axis2=2) / 3.0
    diag = np.diagonal(cov, axis1=1, axis2=2) - mean[:, None]
    p = np.sqrt(((diag ** 2).sum(axis=1) + 2.0 * off) / 6.0)
    safe = np.where(p > 0, p, 1.0)
    b = (cov - mean[:, None, None] * np.eye(3)) / safe[:, None, None]
    half_det = np.clip(np.linalg.det(b) / 2.0, -1.0, 1.0)
    phi = np.arccos(half_det) / 3.0
    l3 = mean + 2.0 * p * np.cos(phi)                                      # largest
    l1 = mean + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)                  # smallest
    l2 = 3.0 * mean - l1 - l3
    m = cov - l1[:, None, None] * np.eye(3)
    crosses = np.stack([np.cross(m[:, 0], m[:, 1]), np.cross(m[:, 0], m[:, 2]), np.cross(m[:, 1], m[:, 2])], axis=1)
    norms = np.linalg.norm(crosses, axis=-1)                               # [P, 3]
    best = np.argmax(norms, axis=1)
    rows = np.arange(cov.shape[0])
    normal = crosses[rows, best] / np.maximum(norms[rows, best], 1e-300)[:, None]
    normal[norms[rows, best] == 0] = (0.0, 0.0, 1.0)                       # isotropic: any direction
    planarity = (l2 - l1) / np.maximum(l3, 1e-12)
    return normal, planarity


@dataclass
class _Data:
    """Point-to-plane terms at the current state: dense normal equations and diagnostics."""
    hessian: np.ndarray      # [4T, 4T] (dense: cheaper to accumulate than sparse, measured)
    gradient: np.ndarray     # [4T]
    residual: np.ndarray     # [C] point-to-plane residuals of correspondences
    frame: np.ndarray        # [C] frame of the query point
    scale: float             # robust scale of residual (metres)
    num_points: np.ndarray   # [T] returns taking part


@dataclass
class _Pairs:
    """Correspondences of one association, at the state they were found at.

    A pair joins a used return ``a`` (row ``src`` of the selection, frame ``fa``) with its
    nearest model point ``b`` of another frame (row ``dst``, frame ``fb``); ``qa``, ``qb`` are
    their body points and ``normal`` the model normal at ``b`` (body frame), all at the state of
    the association (the terms are always evaluated there: nothing is transformed twice).
    """
    src: np.ndarray             # int64 [C] rows into the selection's points
    dst: np.ndarray             # int64 [C]
    fa: np.ndarray              # int64 [C]
    fb: np.ndarray              # int64 [C]
    qa: np.ndarray              # float64 [C, 3] body points of a
    qb: np.ndarray              # float64 [C, 3] body points of b
    normal: np.ndarray          # float64 [C, 3] unit body normal at b
    planarity_weight: np.ndarray    # float64 [C] in [0, 1]
    num_points: np.ndarray      # int64 [T]


def _use_kernel(config: RefineConfig) -> bool:
    """Whether the numba kernels run (``config.kernel == "numba"`` and numba importable)."""
    if config.kernel != "numba":
        return False
    from drivetrack.refine_kernel import NUMBA_AVAILABLE

    return NUMBA_AVAILABLE


_BLAS_CONTROLLER = None


def _single_threaded_blas():
    """A context in which BLAS/LAPACK run on one thread (threadpoolctl; the controller, which
    inspects the loaded libraries, is built once)."""
    global _BLAS_CONTROLLER
    from threadpoolctl import ThreadpoolController

    if _BLAS_CONTROLLER is None:
        _BLAS_CONTROLLER = ThreadpoolController()
    return _BLAS_CONTROLLER.limit(limits=1, user_api="blas")


def _solve_spd(hessian: np.ndarray, rhs: np.ndarray, use_kernel: bool) -> np.ndarray:
    """float64 [n]: ``hessian^-1 rhs`` for the symmetric positive definite normal equations; all NaN
    when the factorisation fails.

    Short clips give dense matrices (every frame pairs with every other): LAPACK's Cholesky on
    one thread (240 unknowns: 0.6 ms; threaded, its CPU cost was 10-25x that on the loaded 2-core
    machine). Long clips give matrices whose rows are zero left of their first coupled frame:
    with the numba kernels, the envelope Cholesky of ``refine_kernel.cholesky_solve`` when the
    envelope holds less than half the lower triangle (1200 unknowns, band 160: 20 ms vs LAPACK's
    39 ms)."""
    n = hessian.shape[0]
    if use_kernel and n > 1:
        first = np.argmax(hessian != 0.0, axis=1)               # first non-zero of each row (<= i)
        envelope = float(np.sum(np.arange(n) - first + 1))
        if envelope < 0.5 * n * (n + 1) / 2:
            from drivetrack import refine_kernel

            return refine_kernel.cholesky_solve(hessian, rhs)
    import scipy.linalg

    with _single_threaded_blas():
        try:
            return scipy.linalg.cho_solve(scipy.linalg.cho_factor(hessian, lower=True, check_finite=False), rhs,
                                          check_finite=False)
        except (np.linalg.LinAlgError, ValueError):
            return np.full(rhs.shape, np.nan)


def _point_jacobian(n: np.ndarray, q: np.ndarray, heading: np.ndarray, tilt: np.ndarray | None = None) -> np.ndarray:
    """float64 [C, 4] (yaw only: d (n . q) / d (c, psi) for body points q = Rz(-psi) (x - c)) or,
    with tilt [C, 2] = (pitch theta, roll phi), float64 [C, 6]: d (n . q) / d (c, psi, theta, phi)
    for q = Rx(-phi) Ry(-theta) Rz(-psi) (x - c), body normals n [C, 3] held fixed.

    With v = Rx q, u = Ry v (= Rz^T (x - c)), k = Rx n, m = Ry k:
    dq/dc = -R^T, so d/dc = -(Rz m); d/dpsi = m . (u_y, -u_x, 0); d/dtheta = k . (-v_z, 0, v_x);
    d/dphi = n . (0, q_z, -q_y)."""
    if tilt is None:
        c, s = np.cos(heading), np.sin(heading)
        return np.stack([-(c * n[:, 0] - s * n[:, 1]), -(s * n[:, 0] + c * n[:, 1]), -n[:, 2],
                         n[:, 0] * q[:, 1] - n[:, 1] * q[:, 0]], axis=-1)
    ct, st, cr, sr = np.cos(tilt[:, 0]), np.sin(tilt[:, 0]), np.cos(tilt[:, 1]), np.sin(tilt[:, 1])
    vy, vz = cr * q[:, 1] - sr * q[:, 2], sr * q[:, 1] + cr * q[:, 2]          # v = Rx q (v_x = q_x)
    ux, uy = ct * q[:, 0] + st * vz, vy                                        # u = Ry v
    ky, kz = cr * n[:, 1] - sr * n[:, 2], sr * n[:, 1] + cr * n[:, 2]          # k = Rx n (k_x = n_x)
    mx, mz = ct * n[:, 0] + st * kz, -st * n[:, 0] + ct * kz                   # m = Ry k (m_y = k_y)
    c, s = np.cos(heading), np.sin(heading)
    return np.stack([-(c * mx - s * ky), -(s * mx + c * ky), -mz, mx * uy - ky * ux,
                     -n[:, 0] * vz + kz * q[:, 0], n[:, 1] * q[:, 2] - n[:, 2] * q[:, 1]], axis=-1)


def _associate(selection: _Selection, center: np.ndarray, heading: np.ndarray, gate_m: float,
               config: RefineConfig, t_count: int, tilt: np.ndarray | None = None) -> _Pairs | None:
    """Correspondences at state (center, heading): one ``cKDTree`` over all used body points,
    one k-nearest query serving both the leave-one-frame-out association (within ``gate_m``) and
    the neighbourhood of each target's PCA normal. None when there is too little to pair."""
    from scipy.spatial import cKDTree

    q, f, rows = selection.select(center, heading, config.inlier_margin_m, config.ground_clearance_m, tilt)
    num_points = np.bincount(f, minlength=t_count).astype(np.int64)
    if q.shape[0] < 4 or np.count_nonzero(num_points) < 2:
        return _Pairs(*(np.zeros(0, np.int64),) * 4, *(np.zeros((0, 3)),) * 3, np.zeros(0), num_points)
    k = int(min(max(config.association_neighbours, config.normal_neighbours), q.shape[0]))
    use_kernel = _use_kernel(config)
    if use_kernel:                                                       # one query serves both uses
        from drivetrack import refine_kernel

        dist, nbr = refine_kernel.knn(q, k)
    else:
        dist, nbr = cKDTree(q).query(q, k=k)
        dist, nbr = dist.reshape(-1, k), nbr.reshape(-1, k)
    ka = min(config.association_neighbours, k)
    other = (dist[:, :ka] <= gate_m) & (f[nbr[:, :ka]] != f[:, None])    # leave-one-frame-out
    has = other.any(axis=1)
    first = np.argmax(other, axis=1)
    src = np.flatnonzero(has)
    dst = nbr[src, first[src]]
    targets, target_of = np.unique(dst, return_inverse=True)
    neighbours = nbr[targets, :min(config.normal_neighbours, k)]
    normal_t, planarity_t = (refine_kernel.normals(q, neighbours) if use_kernel else _normals(q, neighbours))
    weight = np.clip(planarity_t[target_of] / config.min_planarity, 0.0, 1.0)
    return _Pairs(rows[src], rows[dst], f[src], f[dst], q[src], q[dst], normal_t[target_of], weight, num_points)


def _pair_terms(selection: _Selection, pairs: _Pairs | None, center: np.ndarray, heading: np.ndarray,
                config: RefineConfig, t_count: int, normal_equations: bool = True,
                tilt: np.ndarray | None = None) -> _Data:
    """Point-to-plane normal equations of the correspondences ``pairs``, found at state
    (center, heading[, tilt]) (their body points and normals are at that state).

    The residual ``n . (q_a - q_b)`` depends on both poses, so both move (2 x 4 Jacobian non-zeros
    per row, 2 x 6 with tilt, accumulated straight into the dense [DT, DT] normal equations, D = 4
    or 6); the normal rotates with frame b's pose. ``normal_equations=False`` computes the
    residuals only.
    """
    dof = 4 if tilt is None else 6
    n_state = dof * t_count
    num_points = pairs.num_points if pairs is not None else np.zeros(t_count, np.int64)
    if pairs is None or pairs.src.size < 4:
        return _Data(np.zeros((n_state, n_state)), np.zeros(n_state), np.zeros(0), np.zeros(0, np.int64),
                     float("nan"), num_points)
    fa, fb = pairs.fa, pairs.fb
    qa, qb, n = pairs.qa, pairs.qb, pairs.normal
    r = np.einsum("ni,ni->n", n, qa - qb)
    scale = max(1.4826 * float(np.median(np.abs(r))), config.point_sigma_floor_m)
    if not normal_equations:
        return _Data(np.zeros((0, 0)), np.zeros(0), r, fa, scale, num_points)
    w = np.minimum(1.0, config.huber_k * scale / np.maximum(np.abs(r), 1e-12)) / scale ** 2
    w = w * pairs.planarity_weight
    if _use_kernel(config):
        from drivetrack import refine_kernel

        hessian, gradient = refine_kernel.normal_equations(n, qa, qb, fa, fb, w, r, heading, tilt)
        return _Data(hessian, gradient, r, fa, scale, num_points)
    tilt_a, tilt_b = (None, None) if tilt is None else (tilt[fa], tilt[fb])
    jac = np.concatenate([_point_jacobian(n, qa, heading[fa], tilt_a),
                          -_point_jacobian(n, qb, heading[fb], tilt_b)], axis=1)                  # [C, 2D]
    cols = np.concatenate([dof * fa[:, None] + np.arange(dof), dof * fb[:, None] + np.arange(dof)], axis=1)
    blocks = (w[:, None, None] * jac[:, :, None] * jac[:, None, :]).reshape(-1)           # [C * 4D^2]
    flat = (cols[:, :, None] * n_state + cols[:, None, :]).reshape(-1)
    hessian = np.bincount(flat, weights=blocks, minlength=n_state * n_state).reshape(n_state, n_state)
    gradient = np.bincount(cols.reshape(-1), weights=(jac * (w * r)[:, None]).reshape(-1), minlength=n_state)
    return _Data(hessian, gradient, r, fa, scale, num_points)


def _data_terms(selection: _Selection, center: np.ndarray, heading: np.ndarray, gate_m: float,
                config: RefineConfig, t_count: int, normal_equations: bool = True,
                tilt: np.ndarray | None = None) -> _Data:
    """Associate at (center, heading[, tilt]) within ``gate_m`` and evaluate the terms there."""
    pairs = _associate(selection, center, heading, gate_m, config, t_count, tilt)
    return _pair_terms(selection, pairs, center, heading, config, t_count, normal_equations, tilt)


def _world_tilt_offset(world_from_vehicle: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """float64 [T, 2]: (pitch, roll) in the world of a box of heading ``heading`` [T] and no tilt in
    the vehicle frame, i.e. the ego's tilt seen in the box's axes (to first order the world tilt
    of a box is its vehicle-frame tilt plus this)."""
    return tilt_from_poses(world_from_vehicle[:, :3, :3] @ box_from_center_heading(np.zeros((heading.size, 3)),
                                                                                  heading)[:, :3, :3])


def _motion_operator(world_from_vehicle: np.ndarray, timestamps_s: np.ndarray, config: RefineConfig,
                     heading: np.ndarray | None = None):
    """Linear motion-model residuals ``e = S x + e0`` over the stacked state x [DT].

    Rows: for every interior frame, the second divided difference of the world centre (3 rows,
    over ``accel_sigma_mps2``) and of the world heading (1 row, over ``yaw_accel_sigma_radps2``).
    World centre of frame t: ``R_t c_t + p_t``; world heading: ``psi_t + yaw(R_t)`` (unwrapped).
    With ``heading`` [T] given (the labels' headings, radians), the state has D = 6 per frame and
    two more rows: the second divided difference of the world pitch and roll (over
    ``tilt_accel_sigma_radps2``), linearised as ``tilt_t + _world_tilt_offset(t)``: the ego's own
    pitch and roll (braking, turning, bumps) are in ``world_from_vehicle`` and must not be asked of
    the object. Returns (S scipy.sparse csr [D(T-2), DT], e0 float64 [D(T-2)]), or (None, None)
    when T < 3.
    """
    import scipy.sparse as sp

    t_count = timestamps_s.shape[0]
    dof = 4 if heading is None else 6
    if t_count < 3:
        return None, None
    dt = np.diff(timestamps_s)
    dt1, dt2 = dt[:-1], dt[1:]
    coef = np.stack([2.0 / (dt1 * (dt1 + dt2)), -2.0 / (dt1 * dt2), 2.0 / (dt2 * (dt1 + dt2))], axis=-1)  # [T-2, 3]
    rotation = world_from_vehicle[:, :3, :3]
    offset = world_from_vehicle[:, :3, 3]
    yaw_w = np.unwrap(np.arctan2(rotation[:, 1, 0], rotation[:, 0, 0]))
    interior = np.arange(1, t_count - 1)
    frames = interior[:, None] + np.arange(-1, 2)[None, :]                  # [T-2, 3]
    sigma = np.array([config.accel_sigma_mps2, config.accel_sigma_mps2, config.vertical_accel_sigma_mps2])
    rows, cols, vals = [], [], []
    base_row = dof * (interior - 1)
    for k in range(3):                                                      # 3 frames per stencil
        fk = frames[:, k]
        for a in range(3):                                                  # world axis (row)
            for b in range(3):                                              # state centre axis
                rows.append(base_row + a)
                cols.append(dof * fk + b)
                vals.append(coef[:, k] * rotation[fk, a, b] / sigma[a])
        rows.append(base_row + 3)
        cols.append(dof * fk + 3)
        vals.append(coef[:, k] / config.yaw_accel_sigma_radps2)
        if dof == 6:
            for a in (4, 5):                                                # pitch, roll
                rows.append(base_row + a)
                cols.append(dof * fk + a)
                vals.append(coef[:, k] / config.pitch_roll_accel_sigma_radps2)
    S = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(dof * (t_count - 2), dof * t_count))
    e0 = np.zeros(dof * (t_count - 2))
    e0_pos = np.einsum("tk,tki->ti", coef, offset[frames]) / sigma
    e0_yaw = np.einsum("tk,tk->t", coef, yaw_w[frames]) / config.yaw_accel_sigma_radps2
    e0.reshape(-1, dof)[:, :3] = e0_pos
    e0.reshape(-1, dof)[:, 3] = e0_yaw
    if dof == 6:
        tilt_w = _world_tilt_offset(world_from_vehicle, heading)            # [T, 2]
        e0.reshape(-1, dof)[:, 4:] = np.einsum("tk,tka->ta", coef, tilt_w[frames]) / config.pitch_roll_accel_sigma_radps2
    return S, e0


def _check_inputs(vehicle_from_box, size, world_from_vehicle, points_vehicle, point_frame, timestamps_s, name):
    where = f"refine_object_poses({name})" if name else "refine_object_poses"
    vehicle_from_box = np.asarray(vehicle_from_box, dtype=np.float64)
    if vehicle_from_box.ndim != 3 or vehicle_from_box.shape[1:] != (4, 4) or vehicle_from_box.shape[0] < 1:
        raise ValueError(f"{where}: vehicle_from_box must be [T, 4, 4] with T >= 1, got {vehicle_from_box.shape}")
    t_count = vehicle_from_box.shape[0]
    size = np.asarray(size, dtype=np.float64)
    if size.shape == (3,):
        size = np.broadcast_to(size, (t_count, 3))
    if size.shape != (t_count, 3):
        raise ValueError(f"{where}: size must be [3] or [{t_count}, 3], got {size.shape}")
    if not (np.all(np.isfinite(size)) and np.all(size > 0)):
        raise ValueError(f"{where}: size must be finite and positive, got {size[~(np.isfinite(size) & (size > 0)).all(-1)][0].tolist()}")
    world_from_vehicle = np.asarray(world_from_vehicle, dtype=np.float64)
    if world_from_vehicle.shape != (t_count, 4, 4):
        raise ValueError(f"{where}: world_from_vehicle must be [{t_count}, 4, 4], got {world_from_vehicle.shape}")
    for label, arr in (("vehicle_from_box", vehicle_from_box), ("world_from_vehicle", world_from_vehicle)):
        bad = np.flatnonzero(~np.isfinite(arr).all(axis=(1, 2)))
        if bad.size:
            raise ValueError(f"{where}: {label} is not finite at frames {bad[:10].tolist()}")
    points_vehicle = np.asarray(points_vehicle, dtype=np.float64)
    if points_vehicle.ndim != 2 or points_vehicle.shape[1] != 3:
        raise ValueError(f"{where}: points_vehicle must be [M, 3], got {points_vehicle.shape}")
    point_frame = np.asarray(point_frame)
    if point_frame.shape != (points_vehicle.shape[0],) or not (point_frame.size == 0 or np.issubdtype(point_frame.dtype, np.integer)):
        raise ValueError(f"{where}: point_frame must be int [{points_vehicle.shape[0]}], got "
                         f"{point_frame.dtype} {point_frame.shape}")
    point_frame = point_frame.astype(np.int64)
    if point_frame.size and (point_frame.min() < 0 or point_frame.max() >= t_count):
        raise ValueError(f"{where}: point_frame out of range [0, {t_count}): "
                         f"{int(point_frame.min())}..{int(point_frame.max())}")
    if not np.all(np.isfinite(points_vehicle)):
        raise ValueError(f"{where}: points_vehicle has {int((~np.isfinite(points_vehicle).all(-1)).sum())} "
                         f"non-finite rows")
    timestamps_s = np.asarray(timestamps_s, dtype=np.float64)
    if timestamps_s.shape != (t_count,):
        raise ValueError(f"{where}: timestamps_s must be [{t_count}], got {timestamps_s.shape}")
    if np.any(~np.isfinite(timestamps_s)) or np.any(np.diff(timestamps_s) <= 0):
        i = int(np.flatnonzero(~(np.diff(timestamps_s) > 0))[0]) if t_count > 1 else 0
        raise ValueError(f"{where}: timestamps_s must be finite and strictly increasing; frames {i} and {i + 1} "
                         f"have {timestamps_s[i:i + 2].tolist()}")
    return vehicle_from_box, np.ascontiguousarray(size), world_from_vehicle, points_vehicle, point_frame, timestamps_s


def _result(center, heading, label_center, label_heading, world_from_vehicle, tilt=None, **kw) -> RefinedPoses:
    vehicle_from_box = (box_from_center_heading(center, heading) if tilt is None else
                        box_from_center_heading(center, heading, tilt[:, 0], tilt[:, 1]))
    tilt = np.zeros((heading.shape[0], 2)) if tilt is None else tilt
    return RefinedPoses(
        vehicle_from_box=vehicle_from_box, world_from_box=world_from_vehicle @ vehicle_from_box,
        center_vehicle=center, heading=_wrap(heading), pitch=tilt[:, 0].copy(), roll=tilt[:, 1].copy(),
        correction_translation_m=center - label_center,
        correction_rotation_deg=np.rad2deg(_wrap(heading - label_heading)), **kw)


def refine_object_poses(vehicle_from_box: np.ndarray, size: np.ndarray, world_from_vehicle: np.ndarray,
                        points_vehicle: np.ndarray, point_frame: np.ndarray, timestamps_s: np.ndarray,
                        config: RefineConfig | None = None, name: str = "") -> RefinedPoses:
    """Refine one object's per-frame box poses from its own LiDAR (see the module docstring).

    Args:
        vehicle_from_box: float64 [T, 4, 4], labelled box poses, vehicle frame of each frame
            (yaw-only, as ``box_from_center_heading`` makes them from a label; any roll/pitch is
            the start and prior mean of the 6-DOF refinement and dropped by the 4-DOF one).
        size: float64 [3] or [T, 3], box size (length, width, height), metres.
        world_from_vehicle: float64 [T, 4, 4], vehicle pose of each frame.
        points_vehicle: float64 [M, 3], metres, candidate returns near the object (e.g. inside
            the label box grown by ``config.candidate_margin_m``), vehicle frame of their frame.
            Ground, background and other objects among them are tolerated.
        point_frame: int [M], frame index (0..T-1) of each candidate.
        timestamps_s: float64 [T], seconds, strictly increasing.
        config: :class:`RefineConfig` (defaults when None).
        name: object name used in error messages (e.g. ``segment/object_id``).
    Returns:
        :class:`RefinedPoses`; the labels (``refined=False``) when disabled or on fallback.
    Raises:
        ValueError naming the argument, shape or value on malformed input.
    """
    config = config or RefineConfig()
    cpu0 = time.process_time()
    vehicle_from_box, size, world_from_vehicle, points, frame, timestamps_s = _check_inputs(
        vehicle_from_box, size, world_from_vehicle, points_vehicle, point_frame, timestamps_s, name)
    t_count = vehicle_from_box.shape[0]
    label_center, label_heading = center_heading_from_poses(vehicle_from_box)
    label_heading = np.unwrap(label_heading)
    label_tilt = tilt_from_poses(vehicle_from_box)                     # [T, 2], 0 for yaw-only labels
    six = config.pitch_roll_sigma_deg is not None
    dof = 6 if six else 4
    half = size / 2.0
    nan_frames = np.full(t_count, np.nan)

    def labels(reason: str, detail: str, residual=float("nan"), residual_label=float("nan"),
               num_points=None, iterations=0) -> RefinedPoses:
        out = _result(label_center.copy(), label_heading.copy(), label_center, label_heading,
                      world_from_vehicle, tilt=label_tilt.copy(), size=size.copy(), residual_m=residual, residual_label_m=residual_label,
                      residual_per_frame_m=nan_frames.copy(),
                      num_points=np.zeros(t_count, np.int64) if num_points is None else num_points,
                      refined=False, used_fallback=reason not in ("disabled", "labels_consistent"),
                      reason=reason, detail=detail,
                      iterations=iterations, cpu_seconds=time.process_time() - cpu0)
        out.vehicle_from_box = vehicle_from_box.copy()                    # the labels, bit for bit
        out.world_from_box = world_from_vehicle @ out.vehicle_from_box
        return out

    if not config.enabled:
        return labels("disabled", "refinement disabled by configuration")
    order = np.argsort(frame, kind="stable")
    points, frame = points[order], frame[order]
    # fixed per-point priority for the per-frame cap: a hash of the point's coordinates, so the
    # result does not depend on the order of the input rows
    priority = np.modf(np.abs(points @ np.array([12.9898, 78.233, 37.719])) * 43758.5453)[0]

    # Selection at the labels decides whether there is enough to register at all.
    q0 = _body_points(label_center, label_heading, points, frame, label_tilt if six else None)
    at_label = _inside(q0, half[frame], config.inlier_margin_m, config.ground_clearance_m)
    per_frame = np.bincount(frame[at_label], minlength=t_count).astype(np.int64)
    frames_ok = int((per_frame >= config.min_points_per_frame).sum())
    if per_frame.sum() < config.min_points_total or frames_ok < config.min_frames_with_points:
        return labels("too_few_points", f"{int(per_frame.sum())} returns in the label boxes "
                      f"(need {config.min_points_total}); {frames_ok} frames with >= "
                      f"{config.min_points_per_frame} (need {config.min_frames_with_points})",
                      num_points=per_frame)

    S, e0 = _motion_operator(world_from_vehicle, timestamps_s, config, label_heading if six else None)
    prior = [1.0 / config.label_sigma_m ** 2] * 3 + [1.0 / np.deg2rad(config.label_sigma_deg) ** 2]
    if six:
        prior += [1.0 / np.deg2rad(config.pitch_roll_sigma_deg) ** 2] * 2
    prior_w = np.tile(prior, t_count)
    # prior + motion, dense [DT, DT] (the data term couples most pairs of frames: dense anyway),
    # and the motion gradient's constant part S^T e0
    H_fixed = np.diag(prior_w)
    if S is not None:
        H_fixed += (S.T @ S).toarray()
        motion_g0 = S.T @ e0
    use_kernel = _use_kernel(config)
    label_state = np.concatenate([label_center, label_heading[:, None]] + ([label_tilt] if six else []),
                                 axis=1).reshape(-1)
    selection = _Selection(points, frame, priority, half, config.max_points_per_frame, t_count, kernel=use_kernel)

    center, heading = label_center.copy(), label_heading.copy()
    tilt = label_tilt.copy() if six else None
    shrink = max(config.iterations // 2, 1)
    gates = np.concatenate([np.geomspace(config.max_correspondence_m, config.min_correspondence_m, shrink),
                            np.full(max(config.iterations - shrink, 0), config.min_correspondence_m)])
    gates[0] = config.max_correspondence_m
    # The labels' own consistency, measured exactly as the final result is (the first iteration
    # starts from the same terms).
    pairs = _associate(selection, center, heading, config.max_correspondence_m, config, t_count, tilt)
    data = _pair_terms(selection, pairs, center, heading, config, t_count, tilt=tilt)
    residual_label = data.scale
    # The refined residual never drops below the noise floor (``point_sigma_floor_m``): labels
    # within ``min_improvement`` of it are already consistent, whatever the iterations would do.
    if residual_label <= (1.0 + config.min_improvement) * config.point_sigma_floor_m:
        return labels("labels_consistent", f"robust residual {residual_label:.4f} m at the labels: within "
                      f"{config.min_improvement:.0%} of the noise floor {config.point_sigma_floor_m} m",
                      residual=residual_label, residual_label=residual_label, num_points=data.num_points)
    iterations = 0
    for it in range(config.iterations):
        if it > 0:
            data = _data_terms(selection, center, heading, gates[it], config, t_count, tilt=tilt)
        if it > 0 and it == config.early_stop_iteration and \
                residual_label <= (1.0 + config.min_improvement) * data.scale:
            if not data.scale <= config.max_residual_m:          # no rigid surface to register on
                return labels("large_residual", f"robust residual {data.scale:.3f} m after {it} iterations > "
                              f"{config.max_residual_m} m (labels: {residual_label:.3f} m)", residual=data.scale,
                              residual_label=residual_label, num_points=data.num_points, iterations=it)
            return labels("labels_consistent", f"robust residual {residual_label:.4f} m at the labels, "
                          f"{data.scale:.4f} m after {it} iterations: less than {config.min_improvement:.0%} "
                          f"better", residual=data.scale, residual_label=residual_label,
                          num_points=data.num_points, iterations=it)
        state = np.concatenate([center, heading[:, None]] + ([tilt] if six else []), axis=1).reshape(-1)
        # Normal equations of 1/2 (data + prior + motion) in the increment dx.
        g = data.gradient + prior_w * (state - label_state)
        if S is not None:
            g = g + S.T @ (S @ state) + motion_g0
        dx = _solve_spd(data.hessian + H_fixed, -g, use_kernel)
        iterations = it + 1
        if not np.all(np.isfinite(dx)):
            return labels("not_finite", f"non-finite update at iteration {iterations}",
                          residual_label=residual_label, num_points=data.num_points, iterations=iterations)
        dx = dx.reshape(t_count, dof)
        center = center + dx[:, :3]
        heading = heading + dx[:, 3]
        if six:
            tilt = tilt + dx[:, 4:]
        # converged when the step is at the level of re-association jitter (RMS over frames: the
        # largest single-frame step keeps jittering by millimetres as correspondences change)
        small = (np.sqrt(np.mean(np.sum(dx[:, :3] ** 2, axis=1))) < config.tolerance_m
                 and np.rad2deg(np.sqrt(np.mean(np.sum(dx[:, 3:] ** 2, axis=1)))) < config.tolerance_deg)
        if small and gates[it] <= config.min_correspondence_m * 1.0001:
            break
        if small:                                   # converged at this gate: jump to the finest
            gates[it + 1:] = config.min_correspondence_m

    final_pairs = _associate(selection, center, heading, config.max_correspondence_m, config, t_count, tilt)
    final = _pair_terms(selection, final_pairs, center, heading, config, t_count, normal_equations=False, tilt=tilt)
    residual = final.scale
    inlier = np.abs(final.residual) <= config.huber_k * (residual if np.isfinite(residual) else 0.0)
    sq = np.bincount(final.frame[inlier], weights=final.residual[inlier] ** 2, minlength=t_count)
    cnt = np.bincount(final.frame[inlier], minlength=t_count)
    with np.errstate(invalid="ignore", divide="ignore"):
        per_frame_residual = np.where(cnt > 0, np.sqrt(sq / np.maximum(cnt, 1)), np.nan)

    translation = np.linalg.norm(center - label_center, axis=-1)
    rotation = np.rad2deg(np.abs(_wrap(heading - label_heading)))
    if six:      # the tilt's correction counts towards the rotation bound as well
        rotation = np.maximum(rotation, np.rad2deg(np.max(np.abs(tilt - label_tilt), axis=1)))
    if not (np.all(np.isfinite(center)) and np.all(np.isfinite(heading)) and np.isfinite(residual)
            and (tilt is None or np.all(np.isfinite(tilt)))):
        return labels("not_finite", "the refined poses or residual are not finite",
                      residual_label=residual_label, num_points=final.num_points, iterations=iterations)
    if residual > config.max_residual_m:
        return labels("large_residual", f"robust residual {residual:.3f} m > {config.max_residual_m} m "
                      f"(labels: {residual_label:.3f} m)", residual=residual, residual_label=residual_label,
                      num_points=final.num_points, iterations=iterations)
    if translation.max() > config.max_correction_m or rotation.max() > config.max_correction_deg:
        t_bad = int(np.argmax(np.maximum(translation / config.max_correction_m, rotation / config.max_correction_deg)))
        return labels("large_correction", f"frame {t_bad}: correction {translation[t_bad]:.3f} m, "
                      f"{rotation[t_bad]:.2f} deg exceeds {config.max_correction_m} m / "
                      f"{config.max_correction_deg} deg", residual=residual, residual_label=residual_label,
                      num_points=final.num_points, iterations=iterations)
    if residual_label <= (1.0 + config.min_improvement) * residual:
        return labels("labels_consistent", f"robust residual {residual_label:.4f} m at the labels, "
                     f"{residual:.4f} m refined: less than {config.min_improvement:.0%} better",
                     residual=residual, residual_label=residual_label, num_points=final.num_points,
                     iterations=iterations)
    size_out = size.copy()
    extent_detail = ""
    if config.fit_extent and inlier.any():
        # The refined frames agree with each other, so the registered returns of all frames form
        # one body-frame model; grow the box (never shrink, never lower its bottom: ground) so it
        # holds that model. Without this the refined boxes share one small offset (the mean label
        # error, the gauge) and, with point selection at the box faces, lose whole faces in every
        # frame where noisy labels lost them in about half the frames.
        fa = final_pairs.fa[inlier]
        q = final_pairs.qa[inlier]                        # body points at the final state
        half_f = half[fa]
        grow_hi = np.clip(np.max(q - half_f, axis=0) + config.extent_margin_m, 0.0, config.max_extent_growth_m)
        grow_lo = np.clip(np.max(-q - half_f, axis=0) + config.extent_margin_m, 0.0, config.max_extent_growth_m)
        grow_lo[2] = 0.0
        if np.any(grow_hi > 0) or np.any(grow_lo > 0):
            offset = (grow_hi - grow_lo) / 2.0                                   # body frame
            center = center + _from_body(np.broadcast_to(offset, (t_count, 3)), heading, tilt)
            size_out = size + (grow_hi + grow_lo)
            extent_detail = (f"; box grown to the registered returns by {np.round(grow_lo * 100, 1).tolist()} / "
                             f"{np.round(grow_hi * 100, 1).tolist()} cm (-x -y -z / +x +y +z)")
    return _result(center, heading, label_center, label_heading, world_from_vehicle, tilt=tilt, size=size_out,
                   residual_m=residual, residual_label_m=residual_label,
                   residual_per_frame_m=per_frame_residual, num_points=final.num_points, refined=True,
                   used_fallback=False, reason="refined",
                   detail=f"residual {residual_label:.4f} m at the labels -> {residual:.4f} m{extent_detail}",
                   iterations=iterations, cpu_seconds=time.process_time() - cpu0)


def _gather_numpy(points: np.ndarray, laser: np.ndarray, return_index: np.ndarray, lasers, returns,
                  frame_offsets: np.ndarray, box_frame: np.ndarray, box_center: np.ndarray,
                  box_radius: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reference of ``drivetrack.refine_kernel.gather`` (same arguments, same result): the
    selected returns sorted once by (frame, vehicle x), so a box's candidates are a contiguous run
    (a searchsorted on x), then tested on y and z."""
    frame = np.repeat(np.arange(frame_offsets.size - 1), np.diff(frame_offsets))
    selected = np.ones(points.shape[0], dtype=bool)
    if lasers is not None:
        selected &= np.isin(laser, np.asarray(lasers))
    if returns is not None:
        selected &= np.isin(return_index, np.asarray(returns))
    chosen = np.flatnonzero(selected)
    x = points[chosen, 0]
    reach = float(np.abs(box_center[:, 0]).max(initial=0.0)) + float(box_radius.max(initial=0.0))
    span = 2.0 * (max(float(np.abs(x).max(initial=0.0)), reach) + 1.0)      # frames never overlap
    key = frame[chosen].astype(np.float64) * span + x                         # increasing in (frame, x)
    order = np.argsort(key, kind="stable")
    chosen, key = chosen[order], key[order]
    box_frame = np.asarray(box_frame, dtype=np.int64)
    # the runs are widened by a millimetre (the key's rounding), the exact test follows
    lo = np.searchsorted(key, box_frame * span + box_center[:, 0] - box_radius - 1e-3, side="left")
    hi = np.searchsorted(key, box_frame * span + box_center[:, 0] + box_radius + 1e-3, side="right")
    length = np.maximum(hi - lo, 0)
    owner = np.repeat(np.arange(box_frame.size), length)
    first = np.concatenate([[0], np.cumsum(length)[:-1]]).astype(np.int64)
    index = chosen[np.repeat(lo, length) + np.arange(owner.size) - first[owner]]
    near = np.all(np.abs(points[index] - box_center[owner]) <= box_radius[owner, None], axis=-1)
    index, owner = index[near], owner[near]
    order = np.lexsort((index, owner))
    return index[order].astype(np.int64), owner[order].astype(np.int64)


def refine_scene_boxes(scene, config: RefineConfig | None = None, object_ids=None, lasers=None,
                       returns=None, compensate_sweep_motion: bool = True):
    """Refine every object of ``scene`` over its labelled frames; returns boxes usable as labels.

    For each object (``object_ids`` or all), the candidates are the returns (of ``lasers`` /
    ``returns`` when given: ``LaserName`` values and return indices 1|2) inside each label box
    grown by ``config.candidate_margin_m``; :func:`refine_object_poses` runs on them. When the
    scene carries per-return capture times (``LidarReturns.capture_offset_s``) and
    ``compensate_sweep_motion`` holds, candidates are first moved to the frame time with the
    labels' motion, as the track stage does.

    Returns:
        ``(boxes, results)``: a :class:`drivetrack.scene.Boxes` equal to ``scene.boxes`` except for
        the ``center``, ``heading``, ``size`` (and, with 6 DOF, ``pitch`` and ``roll``: 0 on the
        rows of objects not refined) of refined objects, and ``{object_id: RefinedPoses}``.
        Passing ``boxes`` as the scene's labels makes the track stage select points with, and
        carry them by, the refined poses.
    """
    from drivetrack.scene import Boxes

    config = config or RefineConfig()
    boxes, lidar = scene.boxes, scene.lidar
    object_id = boxes.object_id.astype(str)
    ids = sorted(set(object_id.tolist())) if object_ids is None else [str(i) for i in object_ids]
    timestamps_s = (scene.timestamps_micros - scene.timestamps_micros[0]) * 1e-6
    center, heading, size = boxes.center.copy(), boxes.heading.copy(), boxes.size.copy()
    pitch_all, roll_all = boxes.tilt()
    tilted = pitch_all is not None or config.pitch_roll_sigma_deg is not None
    pitch = (np.zeros(len(boxes)) if pitch_all is None else pitch_all.copy()) if tilted else None
    roll = (np.zeros(len(boxes)) if roll_all is None else roll_all.copy()) if tilted else None
    # Returns of moving objects are captured during the sweep, boxes describe the frame time:
    # move each candidate to where its surface was at the frame time (with the labels' motion)
    # before registering, as the track stage does (drivetrack.tracks.sweep_motion).
    offsets = getattr(lidar, "capture_offset_s", None) if compensate_sweep_motion else None
    if offsets is not None:
        from drivetrack.tracks.sweep_motion import points_box_at_capture, scene_box_motion

        box_velocity, box_yaw_rate = scene_box_motion(scene)
    object_rows = []
    for oid in ids:
        rows = np.flatnonzero(object_id == oid)
        if rows.size == 0:
            raise ValueError(f"segment {scene.segment!r}: object {oid!r} has no lidar_box row")
        object_rows.append(rows[np.argsort(boxes.frame[rows], kind="stable")])
    # Candidates of every box of every object at once: the returns of the box's frame within its
    # bounding cube (radius: half the diagonal plus the margin), in (box, row) order.
    all_rows = np.concatenate(object_rows) if object_rows else np.zeros(0, np.int64)
    radius_all = 0.5 * np.linalg.norm(boxes.size[all_rows], axis=-1) + config.candidate_margin_m
    gather = _gather_numpy
    if _use_kernel(config):
        from drivetrack.refine_kernel import gather
    index_all, owner_all = gather(lidar.points_vehicle, lidar.laser, lidar.return_index, lasers, returns,
                                  lidar.frame_offsets, boxes.frame[all_rows], boxes.center[all_rows], radius_all)
    row_start = np.concatenate([[0], np.cumsum([r.size for r in object_rows])]).astype(np.int64)
    bounds = np.searchsorted(owner_all, row_start)
    results = {}
    for k, (oid, rows) in enumerate(zip(ids, object_rows)):
        frames = boxes.frame[rows].astype(np.int64)
        vehicle_from_box = boxes.vehicle_from_box(rows)
        row_tilt = None if pitch_all is None and roll_all is None else np.stack(boxes.tilt(rows), axis=-1)  # [R, 2]
        index = index_all[bounds[k]:bounds[k + 1]]
        owner = owner_all[bounds[k]:bounds[k + 1]] - row_start[k]               # [N] index into rows
        p = lidar.points_vehicle[index]
        if offsets is None:
            local = _body_points(boxes.center[rows], boxes.heading[rows], p, owner, row_tilt)
        else:
            r = rows[owner]
            local = points_box_at_capture(p, offsets[index], boxes.center[r], boxes.heading[r], box_velocity[r],
                                          box_yaw_rate[r], *(boxes.tilt(r)))
        inside = np.all(np.abs(local) <= boxes.size[rows][owner] / 2.0 + config.candidate_margin_m, axis=-1)
        if offsets is not None:        # the compensated return in the vehicle frame: box pose at frame time
            local, owner = local[inside], owner[inside]
            p = _from_body(local, boxes.heading[rows][owner], None if row_tilt is None else row_tilt[owner]) \
                + boxes.center[rows][owner]
            inside = np.ones(owner.size, dtype=bool)
        result = refine_object_poses(vehicle_from_box, boxes.size[rows], scene.world_from_vehicle[frames],
                                     p[inside], owner[inside], timestamps_s[frames], config,
                                     name=f"{scene.segment}/{oid}")
        results[oid] = result
        if result.refined:
            center[rows] = result.center_vehicle
            heading[rows] = result.heading
            size[rows] = result.size
            if tilted:
                pitch[rows], roll[rows] = result.pitch, result.roll
    refined = Boxes(**{k: v for k, v in boxes.__dict__.items()})
    refined.center, refined.heading, refined.size = center, heading, size
    refined.pitch, refined.roll = pitch, roll
    return refined, results
