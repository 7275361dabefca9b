"""The depth stage's knobs: which completer and how, which returns build the sparse maps.

:class:`DepthConfig` owns these knobs' defaults, meaning and checks. :class:`drivetrack.tracks.TrackConfig`
carries the same fields flat (its ``to_dict``/``from_dict`` and the release fingerprint stay
as they are), takes its defaults from here, checks them with :meth:`DepthConfig.check` and gives
them back grouped as ``TrackConfig.depth``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, fields

from drivetrack.waymo.schema import LaserName

__all__ = ["DepthConfig", "DEPTH_FIELDS"]


@dataclass(frozen=True)
class DepthConfig:
    """Configuration of the depth stage (defaults follow the DriveTrack paper's released code).

    Attributes:
        depth_completer: name in the ``drivetrack.depth`` completer registry.
        depth_completer_options: keyword arguments of that completer (e.g. ``max_reach_px``).
        depth_batch: frames per completion batch (the GPU-queue unit).
        depth_lasers: ``LaserName`` names whose returns build the occlusion depth maps (default
            all five lidars).
        depth_returns: return indices that build the depth maps. Default first returns only:
            second returns at object edges put the surface *behind* an occluder into the map
            and make occluded points look visible (measured: docs/benchmarks.md).
        see_through_window_deg: drop from the sparse maps, before completion, the returns the
            camera cannot see because the LiDAR saw them past a nearer surface (over a car
            beside the camera, round a pole): :func:`drivetrack.depth.see_through_returns` with
            quadrant windows of this angle (``f_u * tan(angle)`` pixels) and the track stage's
            ``occlusion_ratio``. The default 0.5 degree (18 px at Waymo's 1920 px width) spans
            about two scan lines of the TOP LiDAR (64 beams over ~20 degrees). None keeps every
            return.
        see_through_min_quadrants: quadrants (of 4) that must hold a nearer return.
        blind_zone_laser: ``LaserName`` of the roof LiDAR beside the cameras (one of
            ``depth_lasers``), or None. Below its lowest scan line in an image (its blind zone round
            the vehicle), the sparse maps are bounded by that line's depth
            (:func:`drivetrack.depth.bound_blind_zone`, column cells of
            ``see_through_window_deg``, 0.5 degree when that is None): a car beside the camera
            that no LiDAR sees there occludes instead of being unknown, and what other lidars
            saw under or round it is dropped.
        depth_object_motion: move each labelled object's returns (those the track stage selects
            for it) from their capture time to the image's pose time on the object's trajectory
            before projecting them (``TrackConfig.time_model="trajectory"`` only): the returns are
            compensated for the ego's motion only, so a car moving beside the ego, captured tens
            of milliseconds from the exposure, otherwise lands tens of centimetres off in the map.
    """
    depth_completer: str = "nearest"
    depth_completer_options: dict = field(default_factory=dict, hash=False)
    depth_batch: int = 16
    depth_lasers: tuple[str, ...] = ("TOP", "FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR")
    depth_returns: tuple[int, ...] = (1,)
    see_through_window_deg: float | None = 0.5
    see_through_min_quadrants: int = 3
    blind_zone_laser: str | None = "TOP"
    depth_object_motion: bool = True

    def __post_init__(self):
        for name, value in self.check({f.name: getattr(self, f.name) for f in fields(self)}).items():
            object.__setattr__(self, name, value)
        if self.depth_batch < 1:   # TrackConfig checks it with chunk_points
            raise ValueError(f"DepthConfig.depth_batch must be >= 1, got {self.depth_batch}")

    @staticmethod
    def check(values: dict, where: str = "DepthConfig") -> dict:
        """The depth knobs in ``values`` normalised (tuples, a dict of options); raises ValueError
        naming ``where`` (the config class) and the field, expected and found, when one is invalid."""
        out = dict(values)
        lasers = out["depth_lasers"]
        if isinstance(lasers, str):
            raise ValueError(f"{where}.depth_lasers must be a sequence of names, got the string {lasers!r}")
        out["depth_lasers"] = tuple(lasers)
        for value in out["depth_lasers"]:
            if value not in LaserName.__members__:
                raise ValueError(f"{where}.depth_lasers: unknown LaserName {value!r}; "
                                 f"expected one of {sorted(LaserName.__members__)}")
        out["depth_returns"] = tuple(int(r) for r in out["depth_returns"])
        if not set(out["depth_returns"]) <= {1, 2} or not out["depth_returns"]:
            raise ValueError(f"{where}.depth_returns must be a non-empty subset of (1, 2), "
                             f"got {out['depth_returns']}")
        window = out["see_through_window_deg"]
        if window is not None and not 0 < window < 45:
            raise ValueError(f"{where}.see_through_window_deg must be None or in (0, 45) degrees, got {window}")
        if out["see_through_min_quadrants"] not in (1, 2, 3, 4):
            raise ValueError(f"{where}.see_through_min_quadrants must be 1..4, got {out['see_through_min_quadrants']}")
        if out["blind_zone_laser"] is not None and out["blind_zone_laser"] not in out["depth_lasers"]:
            raise ValueError(f"{where}.blind_zone_laser must be None or one of depth_lasers "
                             f"{out['depth_lasers']}, got {out['blind_zone_laser']!r}")
        if not isinstance(out["depth_object_motion"], bool):
            raise ValueError(f"{where}.depth_object_motion must be true or false, got {out['depth_object_motion']!r}")
        out["depth_completer_options"] = dict(out["depth_completer_options"])
        return out

    @property
    def depth_laser_values(self) -> tuple[int, ...]:
        return tuple(int(LaserName[name]) for name in self.depth_lasers)


#: The depth knobs, in :class:`DepthConfig`'s (and ``TrackConfig``'s) field order.
DEPTH_FIELDS = tuple(f.name for f in fields(DepthConfig))
