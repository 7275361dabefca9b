"""Configuration and outcomes of the pose refinement: :class:`RefineConfig`, :class:`RefineReason`."""
from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from enum import StrEnum

import numpy as np

__all__ = ["RefineConfig", "RefineReason", "REFINE_REASONS"]


class RefineReason(StrEnum):
    """``RefinedPoses.reason`` values (``refine_reason`` in the objects table). ``refined``: refined
    poses returned; ``disabled``: refinement off by configuration; ``labels_consistent``: the labels
    are already as consistent with the LiDAR as the refined poses (within ``min_improvement``), so
    they are kept unchanged; ``static``: the labels show the object standing still, it keeps one
    world pose (the labels' mean, :mod:`drivetrack.refine.static`) and is not registered frame by
    frame; the others are fallbacks to the labels (``used_fallback``)."""
    REFINED = "refined"
    DISABLED = "disabled"
    LABELS_CONSISTENT = "labels_consistent"
    STATIC = "static"
    TOO_FEW_POINTS = "too_few_points"
    LARGE_RESIDUAL = "large_residual"
    LARGE_CORRECTION = "large_correction"
    NOT_FINITE = "not_finite"


#: The values of :class:`RefineReason`, in its order.
REFINE_REASONS = tuple(reason.value for reason in RefineReason)


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
        normal_neighbours: model points in the PCA giving each model normal while a frame's
            subset holds 120 returns or fewer; more in proportion when it holds more
            (:func:`drivetrack.refine.terms.normal_neighbours`: the same patch of surface).
        min_planarity: a correspondence's weight is scaled by the planarity of its model
            neighbourhood ((l2 - l1) / l3 of the PCA eigenvalues) over this, capped at 1: points
            on a scan line or an edge, whose normal is undefined, count less or not at all.
        association_neighbours: nearest model points examined to find one from another frame.
        max_points_per_frame: at most this many returns per frame take part (a fixed
            pseudo-random subset, deterministic); bounds the cost on near objects. 400: a car
            seen from behind or side-on is pinned along its faces only by the few returns at
            their edges, which a smaller subset mostly leaves out (docs/refinement.md, "Returns
            per frame"; 120 before).
        sample_normals: that subset shared among the directions the returns' surfaces face
            (normal-space sampling, ``drivetrack.refine.select.normal_priority``): about a third
            each from returns facing along the label box, across it and up, where a frame has
            them. True (default): a car seen side-on keeps the returns of its front or rear face,
            seen at a grazing angle, which alone fix it along the road and which a uniform subset
            mostly leaves out (docs/refinement.md, "Normal-space sampling"). False: uniform.
        sample_normals_screen: how many of each frame's returns the normal-space sampling
            looks at, in multiples of ``max_points_per_frame`` (the first by the fixed hash); each
            gets its normal from its neighbours among them. 3 (default); 12 (every candidate of a
            near car) measured better on one real-log world and on the small worlds' mean, worse
            on the medium box-car worlds (docs/refinement.md, "Normal-space sampling").
        sample_voxel_m: instead, that subset spread evenly over the object's surface: one return
            per cube of this side (metres) before a second from any
            (``drivetrack.refine.select.spread_priority``); takes precedence over
            ``sample_normals``. None (default): not used. 0.1 measured better on the small hard
            world and worse on the medium one (docs/refinement.md, "Even subsets").
        label_sigma_m, label_sigma_deg: the labels' per-frame noise (prior strength).
        accel_sigma_mps2, vertical_accel_sigma_mps2, yaw_accel_sigma_radps2: motion model
            stiffness: horizontal, vertical (world z; roads are smooth and the LiDAR sees little
            of a roof, so z is the least observed direction) and yaw acceleration.
        jerk_sigma_mps3: the stiffness (m/s^3) of a second motion term on the world centre's
            jerk (6 x the third divided difference over four frames, all three axes): it steadies
            a weakly observed direction (along a box seen side-on) over many frames without
            penalising a steady acceleration or braking, as a stiffer acceleration term would.
            5 (default) still follows a car braking hard from one frame to the next (2 smooths
            that away); with 5 cm labels it gains on 2 s segments and, with cars shaped as a
            body and a cabin, on 4 s ones; on 1 s box-car segments it lost on one world and
            gained on another (docs/refinement.md, "Jerk"). None: off. Exact labels are kept
            either way. With ``jerk_sigma_choices_mps3`` this is the loosest choice.
        jerk_sigma_choices_mps3, jerk_evidence_nats: stiffer jerk terms (m/s^3) a wheeled object
            (a vehicle or a cyclist; a pedestrian's centre sways with its steps) gets
            when its labels do not speak against them: the stiffest of these and
            ``jerk_sigma_mps3`` whose evidence (the marginal likelihood of the labels' horizontal
            world centres under the motion model) is within ``jerk_evidence_nats`` of the best
            (:func:`drivetrack.refine.motion.jerk_sigma_from_labels`; the choice is
            ``refine_jerk_sigma_mps3`` in ``stats/objects.parquet``). A car that keeps its speed
            or brakes steadily gets the stiff term, which steadies what its returns do not
            observe (along a car seen side-on); one that starts or stops braking keeps
            ``jerk_sigma_mps3``. Default (1, 2) and 3 nats (since 2026-12-03, forty-fourth
            session; docs/refinement.md "The jerk term's stiffness from the labels"); ``()``:
            ``jerk_sigma_mps3`` for every object (before).
        extent_sigma_m: the extent term of wheeled objects (:mod:`drivetrack.refine.extent`):
            in each frame that sees a side, the first and last returns along the body's x axis
            are the object's ends; each frame's ends against the median ends over the frames
            measure its position along its heading with this sigma (m). A box-like side face
            alone does not pin that (docs/refinement.md, "Extent": 0.01 measured mixed, large
            gains and losses by world, so off by default). Not applied to an object
            whose returns were found to carry range noise (``sweep_surface_max_m``: they were
            moved onto their sweep's surface), whose ends scatter along the side. None: off.
        slip_sigma_mps: the no-side-slip prior of wheeled objects (``refine_object_poses(...,
            wheeled=True)``; ``refine_scene_boxes``: VEHICLE and CYCLIST): between consecutive
            frames, the lateral velocity (m/s) of the point on the box's long axis that drives
            along the heading (a rear axle: its offset from the centre is an unknown of the solve)
            has this sigma. It ties a car's position across its rear or front face, which the
            returns of that face do not pin, to its heading, which they do (docs/refinement.md,
            "No side slip"). 0.02 m/s: steady-state tyre slip grows with the lateral
            acceleration and at a steady speed is the same as moving that point; what is left
            when the speed changes on a curve is about 0.01-0.02 m/s. None: off (before
            2026-11-28, twentieth session).
        pitch_roll_sigma_deg: None: 4 degrees of freedom per frame (centre, heading: the labels'
            parametrisation; a refined box is yaw-only like a label). A number: 6 (and pitch,
            roll), with a prior of this sigma towards the labels' tilt (0 for ``lidar_box``
            labels: level in the vehicle frame); refined boxes then carry ``pitch``/``roll``.
        pitch_roll_accel_sigma_radps2: (6 DOF) motion model stiffness of the box's pitch and
            roll in the *world* (the ego's own pitch and roll are taken out with its pose).
        static_objects: give an object the labels show standing still one world pose, the robust
            mean of its labels' (:mod:`drivetrack.refine.static`), before registration; its box is
            grown to hold its returns when the registration keeps that pose.
        static_speed_mps, static_fit_speed_mps: an object is static when its labelled speed stays
            under ``static_speed_mps`` in every frame and the least-squares line through
            its labels' world centres over time moves slower than ``static_fit_speed_mps``
            (``static_speed_mps`` when the labels carry no speed) and by less than
            ``static_max_drift_m`` over the object's labels. A static object is not registered
            frame by frame (reason ``static``).
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
        motion_passes: (``refine_scene_boxes``, with per-return capture times) how many times the
            objects are registered: the first pass moves each candidate return to its box's time
            with the labels' finite-difference motion, each further pass with the motion of the
            boxes registered so far (objects whose registration was applied); 1 = labels only.
        motion_window: that motion is the least-squares slope of each box's centre and yaw over
            its object's boxes up to this many either side in time (1: central differences).
        occluders: (``drivetrack.annotate.refine_scene``) refine, besides the objects that are
            annotated, the labelled objects that may hide part of an annotated clip
            (:func:`drivetrack.tracks.core.occluding_objects`): the occlusion z-buffer draws their
            returns carried by their boxes, so noisy labels blur their surface as they would a
            tracked object's (docs/refinement.md, "Occluders").
        sweep_surface_max_m: (``refine_scene_boxes``) before registering a moving object, each
            candidate return moves along its own lidar ray onto the surface of its own sweep's
            candidates round it, by at most this much (metres; None: off), when the returns show
            range noise (:func:`drivetrack.visibility.points_on_sweep_surface`; exact ranges stay
            bit for bit): the registration then matches surfaces instead of each return's
            centimetres of noise; whether the result beats the labels is still decided on the
            returns as measured (docs/refinement.md, "Range noise").
        ground_ring: leave out of an object's candidates the returns within ``ground_clearance_m``
            of the ground measured round each label box (``drivetrack.boxes.ground_under_boxes``)
            where the box reaches more than 3 cm below it (a label drawn wider than its object:
            the road's returns would be registered as the object's and pull it back along its
            path). True (default); False: the clearance is over the box's bottom only.
        exclusive_returns: leave out of an object's candidates the returns another object's label
            box of the frame holds more deeply (``drivetrack.boxes.claimed_by_other_boxes``): a
            pedestrian beside a car, cars queueing. True (default).
        kernel: ``numba`` (default: k-nearest search, normals and normal equations in the fused
            kernels of ``drivetrack.refine.kernel``) or ``numpy`` (the scipy/numpy reference,
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
    max_points_per_frame: int = 400
    sample_normals: bool = True
    sample_normals_screen: int = 3
    sample_voxel_m: float | None = None
    label_sigma_m: float = 0.05
    label_sigma_deg: float = 1.0
    accel_sigma_mps2: float = 2.0
    vertical_accel_sigma_mps2: float = 0.3
    yaw_accel_sigma_radps2: float = 1.0
    jerk_sigma_mps3: float | None = 5.0
    jerk_sigma_choices_mps3: tuple[float, ...] = (1.0, 2.0)
    jerk_evidence_nats: float = 3.0
    slip_sigma_mps: float | None = 0.02
    extent_sigma_m: float | None = None
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
    static_objects: bool = True
    occluders: bool = True
    motion_passes: int = 2
    motion_window: int = 2
    static_speed_mps: float = 0.1
    static_fit_speed_mps: float = 0.25
    static_max_drift_m: float = 0.2
    fit_extent: bool = True
    extent_margin_m: float = 0.02
    max_extent_growth_m: float = 0.1
    sweep_surface_max_m: float | None = 0.1
    ground_ring: bool = True
    exclusive_returns: bool = True
    kernel: str = "numba"

    def __post_init__(self):
        positive = ("iterations", "max_correspondence_m", "min_correspondence_m", "huber_k",
                    "point_sigma_floor_m", "min_planarity", "label_sigma_m", "label_sigma_deg", "accel_sigma_mps2",
                    "yaw_accel_sigma_radps2", "vertical_accel_sigma_mps2", "pitch_roll_accel_sigma_radps2",
                    "max_residual_m", "max_correction_m",
                    "max_correction_deg", "max_points_per_frame", "tolerance_m", "tolerance_deg", "static_speed_mps",
                    "static_fit_speed_mps", "static_max_drift_m")
        for name in ("motion_passes", "motion_window", "sample_normals_screen"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool) and value >= 1):
                raise ValueError(f"RefineConfig.{name} must be an integer >= 1, got {value!r}")
        for name in positive:
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"RefineConfig.{name} must be a positive number, got {value!r}")
        for name in ("sample_normals", "ground_ring", "exclusive_returns"):
            if not isinstance(getattr(self, name), (bool, np.bool_)):
                raise ValueError(f"RefineConfig.{name} must be True or False, got {getattr(self, name)!r}")
        if self.sample_voxel_m is not None and not (isinstance(self.sample_voxel_m, (int, float))
                                                    and np.isfinite(self.sample_voxel_m) and self.sample_voxel_m > 0):
            raise ValueError(f"RefineConfig.sample_voxel_m must be None or a positive number, got {self.sample_voxel_m!r}")
        if self.extent_sigma_m is not None and not (isinstance(self.extent_sigma_m, (int, float))
                                                    and not isinstance(self.extent_sigma_m, bool)
                                                    and np.isfinite(self.extent_sigma_m) and self.extent_sigma_m > 0):
            raise ValueError(f"RefineConfig.extent_sigma_m must be None or a positive number, got {self.extent_sigma_m!r}")
        if self.slip_sigma_mps is not None and not (isinstance(self.slip_sigma_mps, (int, float))
                                                    and np.isfinite(self.slip_sigma_mps) and self.slip_sigma_mps > 0):
            raise ValueError(f"RefineConfig.slip_sigma_mps must be None or a positive number, got {self.slip_sigma_mps!r}")
        if self.jerk_sigma_mps3 is not None and not (isinstance(self.jerk_sigma_mps3, (int, float))
                                                     and np.isfinite(self.jerk_sigma_mps3) and self.jerk_sigma_mps3 > 0):
            raise ValueError(f"RefineConfig.jerk_sigma_mps3 must be None or a positive number, got {self.jerk_sigma_mps3!r}")
        choices = self.jerk_sigma_choices_mps3
        if not isinstance(choices, (tuple, list)) or not all(
                isinstance(c, (int, float)) and not isinstance(c, bool) and np.isfinite(c) and c > 0 for c in choices):
            raise ValueError(f"RefineConfig.jerk_sigma_choices_mps3 must be a list of positive numbers (m/s^3), got "
                             f"{choices!r}")
        object.__setattr__(self, "jerk_sigma_choices_mps3", tuple(float(c) for c in choices))
        if not (isinstance(self.jerk_evidence_nats, (int, float)) and not isinstance(self.jerk_evidence_nats, bool)
                and np.isfinite(self.jerk_evidence_nats) and self.jerk_evidence_nats >= 0):
            raise ValueError(f"RefineConfig.jerk_evidence_nats must be a number >= 0, got {self.jerk_evidence_nats!r}")
        for name in ("extent_margin_m", "max_extent_growth_m", "candidate_margin_m", "inlier_margin_m", "min_points_total", "min_points_per_frame",
                     "min_improvement", "early_stop_iteration"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value >= 0):
                raise ValueError(f"RefineConfig.{name} must be >= 0, got {value!r}")
        if self.sweep_surface_max_m is not None and not (
                isinstance(self.sweep_surface_max_m, (int, float)) and not isinstance(self.sweep_surface_max_m, bool)
                and np.isfinite(self.sweep_surface_max_m) and self.sweep_surface_max_m > 0):
            raise ValueError(f"RefineConfig.sweep_surface_max_m must be None or a positive number of metres, got "
                             f"{self.sweep_surface_max_m!r}")
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


def _use_kernel(config: RefineConfig) -> bool:
    """Whether the numba kernels run (``config.kernel == "numba"`` and numba importable)."""
    if config.kernel != "numba":
        return False
    from drivetrack.numba_compat import NUMBA_AVAILABLE

    return NUMBA_AVAILABLE
