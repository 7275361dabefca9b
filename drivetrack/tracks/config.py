"""Every knob of the track stage, in one dataclass built once at the entry point.

The depth stage's knobs are defined, defaulted and checked by :class:`drivetrack.depth.config.DepthConfig`;
``TrackConfig`` carries them flat so that its serialisation (``to_dict``, run.json, the release
fingerprint) is one flat dict, and gives them back grouped as :attr:`TrackConfig.depth`.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields

from drivetrack.depth.config import DEPTH_FIELDS, DepthConfig
from drivetrack.visibility.facing import NEIGHBOURHOODS, NORMAL_TRANSFERS
from drivetrack.waymo.schema import BoxType, CameraName, LaserName

__all__ = ["TrackConfig", "FOV_RUN_POLICIES", "TRACK_KERNELS"]

#: What to do when an object's in-view frames form more than one continuous run.
#: ``reject``: the paper's rule (the object may not leave the image and come back), counted under
#: ``label_gap`` / ``image_gap`` / ``left_and_returned``; ``longest``: keep the longest run.
FOV_RUN_POLICIES = ("reject", "longest")

#: Implementations of the track stage's global-shutter inner loop (``TrackConfig.kernel``).
TRACK_KERNELS = ("numba", "numpy")
#: How the track stage decides occlusion (``TrackConfig.occlusion``): ``surface`` = depth map +
#: back faces + z-buffer of the other labelled objects; ``depth-ratio`` = the paper's depth test alone.
OCCLUSION_METHODS = ("surface", "depth-ratio")

#: How an occluder return's splat radius is chosen (``TrackConfig.surfel_radius_from``): one fixed
#: radius, or from the local spacing of the object's returns.
SURFEL_RADII = ("fixed", "spacing")

_DEPTH = DepthConfig()


@dataclass(frozen=True)
class TrackConfig:
    """Configuration of the depth and track stages (defaults follow the DriveTrack paper).

    Attributes:
        object_types: ``BoxType`` names annotated (default vehicles only).
        occluder_types: ``BoxType`` names whose labelled objects hide the annotated ones in the
            occlusion z-buffer whether or not they are annotated (default every labelled type:
            a pedestrian, cyclist or sign in front of a car hides it as a car would; with
            vehicles alone in the z-buffer their occlusion fell to the depth map's 5% rule).
            Their returns are selected and their poses refined like the annotated objects';
            ``object_types`` always occlude too. Used under ``occlusion="surface"``.
        cameras: ``CameraName`` names annotated (default the three front cameras; all five may be
            named, SIDE_LEFT / SIDE_RIGHT are 1920x886; docs/time.md).
        lasers: ``LaserName`` names whose returns form the object point clouds (default all).
        returns: return indices used for object points (1 = first, 2 = second).
        min_frames: minimum length, in frames, of the continuous run in view (paper: 24).
        fov_runs: see :data:`FOV_RUN_POLICIES`.
        fov_samples_per_axis: a box is "in view" at a frame when one of its
            ``n**3`` grid samples (corners, edges, faces, interior) projects inside the image in
            front of the camera with trusted distortion.
        max_camera_distance_m: the box centre must come within this distance of the *camera
            centre* at some frame of the clip (paper: 20 m; the released code used 50 m).
        box_margin_m: grows (> 0) or shrinks (< 0) the box when selecting its LiDAR points.
        ground_clearance_m: points less than this above the box bottom are dropped (ground).
        occlusion_ratio: a point is occluded at a frame when the depth map there is known and
            ``depth < occlusion_ratio * z`` (z = the point's z-depth from the camera). 0.95 is the
            released code's factor; 1.0 is a strict test.
        depth_lookup_px, depth_lookup_min_jitter_m: with ``occlusion: surface``, where the labels
            of the segment jitter by at least ``depth_lookup_min_jitter_m`` (metres, per axis:
            the label centres' second differences over three frames, as delivered,
            :func:`drivetrack.tracks.plan.label_jitter_m`;
            None: always), the depth map's surface at a point is the farthest over its max-of-4
            pixels and every pixel within ``depth_lookup_px`` of them (0: the max-of-4 alone,
            the paper's). The completed map spreads each outline a pixel or two past it: with
            exact labels the own-box and other-object rules take that back (a grown look-up only
            loses true occlusions there), with jittering labels much of it hid what lies beside
            the outline (measured; why is not settled). Default 1 px from 1 cm (2026-12-03,
            forty-first session; docs/visibility.md "The depth map's outlines under label
            noise"); with exact labels the max-of-4 stays.
        back_face_max_deg: a point is also occluded at a frame when its surface normal (from the
            object's own returns, :mod:`drivetrack.visibility.facing`) makes this angle or more
            with the direction to the camera: its face turns away and its own object hides it.
            None: the depth test alone (the paper's method). Used under ``occlusion="surface"``.
        own_surface_margin_m: with the back-face test on, the depth-map test ignores a surface
            whose point on the ray to the tracked point lies inside the object's own box grown by
            this margin (metres): the depth maps are completed by nearest neighbour, which smears
            an object's nearer returns over its own farther, visible points (a roof above its
            rear face); whether an object hides its own point is the back-face test's call
            (:func:`drivetrack.visibility.own_surface`), at points whose normal is reliable (the
            depth map still decides for the others). None: every surface counts (before).
        own_surface_max_gap_m: ... only when that surface point lies at most this far (metres)
            in front of the tracked point along its ray, or farther but with the ray from it to
            this far in front of the point running outside the box itself (through the margin:
            the map's spread over a roof seen at a grazing angle); where that stretch of the ray
            passes through the box, it is a part of the object itself in front of the point (a
            cabin in front of a bonnet or boot, a mirror, a truck's cab), which a box never has
            but real vehicles do, and the map hides the point. None: no limit. Measured in
            docs/visibility.md ("Vehicles are not boxes", "The gap limit only where the ray
            passes through the box itself").
        depth_defers_to_zbuffer: under ``occlusion="surface"``, with the z-buffer of other objects
            and the own-box rule on, the depth-map test also ignores a surface whose point on the
            ray lies inside another labelled object's box (posed for the image, grown by
            ``own_surface_margin_m``): the map spreads that object's returns a few pixels beyond
            its outline by nearest neighbour, while the z-buffer draws it from its own surface
            (:func:`drivetrack.visibility.other_surface`). False: the map hides there too (before
            2026-11-26, fifth session; docs/visibility.md).
        normals_from: where the back-face normals' neighbourhoods come from: ``segment`` (default)
            all the object's returns over the segment in its box frame, thinned to cubes of half
            ``surfel_radius_m`` (the z-buffer's surface; needs ``time_model="trajectory"``, the
            clip's otherwise; each cube's mean, :func:`drivetrack.tracks.core.segment_normals_cloud`),
            or ``clip`` the clip's returns. ``normal_neighbours``: k of the k-nearest-neighbour PCA
            (default 30; 12 before 2026-11-27, eleventh session: with 2 cm of lidar range noise
            the normals of 12 scattered by tens of degrees, docs/visibility.md). The normals are
            those of the cloud's points, each tracked point taking its nearest's (since the twelfth
            session; the tracked point's own neighbourhood among the cloud before).
        normal_neighbourhood: ``shifted`` (default) each cloud point's normal is that of the
            flattest of its neighbours' neighbourhoods whose plane passes through it, so a point
            near a sharp edge takes its own face's normal; ``centred`` its own neighbourhood's,
            which straddles the edge (before 2026-11-27, twelfth session;
            :func:`drivetrack.visibility.cloud_normals`, docs/visibility.md "Shifted neighbourhoods").
        normal_transfer: how a tracked point takes a normal from the segment cloud's:
            ``ray`` (default since 2026-12-03, thirty-seventh session): where the object's
            returns carry range noise (its normals refitted on coarser cubes,
            ``normal_noise_cubes``), the face its lidar ray enters by among those cloud points'
            (:meth:`drivetrack.visibility.CloudNormals.on_ray`: range noise moves a return along
            its ray, which is exact; docs/visibility.md "Normals from the face the ray enters
            by"), elsewhere ``plane``'s; ``plane`` (default 2026-11-28 to 2026-12-03) that of the cloud point,
            among the 12 nearest its nearest cloud point, whose plane passes nearest it, so a
            point a centimetre from an edge keeps its own face's
            (:meth:`drivetrack.visibility.CloudNormals.on_plane`); ``nearest`` its nearest
            cloud point's (before; a 2.5 cm
            cube's mean across the edge gave the other face's normal: docs/visibility.md
            "Normals near an edge").
        normal_noise_cubes: where an object's returns carry range noise, its back-face normals
            are fitted on the means of cubes of this many times the cloud's spread about its
            planes (at most 12 cm) instead of the 2.5 cm cubes, which stack in a slab under the
            noise (:func:`drivetrack.visibility.facing.noise_aware_normals`; docs/visibility.md
            "Normals under range noise"). Default 12 (since 2026-11-29, twenty-ninth session;
            measured); None: the fine cubes always. Exact ranges are left bit for bit.
        normal_precise_m: a cloud point whose chosen plane misses it beyond that plane's own
            spread, or is no plane that fits its neighbourhood and passes through it within this
            (metres), takes the flattest of its neighbours' chosen planes that does, of any tilt:
            the top scan line of a sparsely sampled face just under a densely sampled one (a rear
            face under the roof) had taken the dense face's normal
            (:func:`drivetrack.visibility.cloud_normals`; docs/visibility.md "Planes that pass
            through their points"). Default 0.0005 (since 2026-12-02, thirty-third session); 0:
            off (before).
        box_face_normals_m: a point whose normal is unreliable (too few or too collinear
            neighbours: a roof or a side the lidar sees at a grazing angle) but which lies within
            this distance (metres) of exactly one face of its label box, away from its edges,
            takes that face's outward normal for the back-face test and the own-box rule
            (:func:`drivetrack.visibility.with_box_face_normals`). None: such points stay
            unreliable and the depth map decides for them, the own-box rule only where the ray
            from the map's surface to the point misses the box itself (docs/visibility.md,
            "Unreliable normals").
        occlusion: how occlusion is decided (:data:`OCCLUSION_METHODS`). ``surface`` (default):
            the depth-map test, plus back faces (``back_face_max_deg``), plus the z-buffer of the
            other labelled objects' returns (:mod:`drivetrack.visibility.zbuffer`: hidden when
            another object's surface lies nearer than ``z - (occluder_tolerance_m +
            occluder_tolerance_rel * z)`` at the point's pixel). ``depth-ratio``: the paper's
            method exactly (the depth-map test alone).
        occluder_tolerance_m, occluder_tolerance_rel: that tolerance (metres, fraction of z).
            Default 0.15 m and 0: a footprint's 5 cm, the returns' range noise and the boxes'
            few centimetres of pose error, none of which grows with the distance (0.3 m + 2%
            before 2026-11-26: a pole 0.5 m in front of a car 25 m away hid nothing;
            docs/visibility.md).
        ambiguity_m, ambiguity_deg: an occlusion decision this close to flipping (metres of depth
            from the depth-map test's or the z-buffer's threshold, degrees from
            ``back_face_max_deg``) is counted as ambiguous (``num_ambiguous_occlusion`` in
            ``stats/objects.parquet``; a gate bounds it); the units of ``occlusion_margin``.
        occlusion_margins: keep each kept point-frame's occlusion margin (how far its decision
            was from flipping, :class:`drivetrack.tracks.core.ObjectTracks`) as the clip's
            optional ``occlusion_margin`` array (float16 [N, T]); the per-clip ambiguous count
            is computed from the margins either way.
        surface_snap_max_m: each tracked return moves along its own lidar ray onto its object's
            surface, at most this far (metres; None: off, each return where the lidar put it, as
            before 2026-11-28): the mean, along the return's normal, of the object's returns round
            it of its own sweep and the two before and after it
            (:func:`drivetrack.visibility.points_on_surface`). Real returns carry
            centimetres of range noise, and at a few metres a centimetre across the camera's ray
            is pixels. Only when a clip's returns show range noise (an estimate of 2 mm or more:
            exact ranges are left bit for bit) and under ``occlusion="surface"`` with the
            segment's normals (``normals_from: segment``, the trajectory). docs/visibility.md
            "Returns moved onto their surface".
        surface_snap_margin_m: that surface is drawn from the returns inside the label boxes grown
            by this much (metres): where a box is tight, the returns inside it are those whose
            noise moved them inwards, and their mean lies inside the true surface.
        surface_snap_segment: with ``surface_snap_max_m``, also move the returns each object's
            surface over the segment is drawn from (its z-buffer splats as another object's
            occluder and its own, its hull and roof fill) onto that surface the same way, where
            the object's normals saw range noise (:func:`drivetrack.tracks.core.segment_surface`),
            and take the part of its box it fills from the returns so moved
            (:func:`drivetrack.tracks.core.segment_solid_bounds`): seen from many places over a
            segment, the returns' noise along their rays thickens the measured shell by
            centimetres all round, and every outline drawn from it grows by as much (False: the
            returns as measured, as before 2026-12-03). docs/visibility.md "Occluder surfaces
            under range noise".
        segment_margin_m: under ``time_model="trajectory"``, make each object's surface over the
            segment (the returns its z-buffer splats are drawn from, its convex hull, roof fill
            and solid part, and the cloud its back-face normals are fitted on) of its returns
            inside its label boxes grown by this much (metres); the tracked points stay those
            inside the boxes grown by ``box_margin_m``. None (default): the tracked points'
            selection. A box drawn tight has its object's outer returns on its faces, and carried
            into the box frame many land a few millimetres outside (a pedestrian's surface held
            14,966 of its 31,405 returns, a car's 43,486 of 58,927): with no margin
            the occluders' faces have holes, through which hidden points are called visible
            (medium hard world, exact labels: 3,405 wrong calls, 2,036 with 0.01, 2,024 with 0.02
            or 0.1; cabin cars 10,848 -> 9,936). Not the default: with 2 cm of range noise on
            the same tight labels a margin takes in the returns the noise moved outwards, the
            occluders' splats stand out of their outline and hide the visible points beside them
            (6,620 -> 7,739 with 0.01, 11,080 with 0.02, 12,298 with 0.1); with 5 cm label noise
            and 2 cm range noise 40,890 -> 40,333 with 0.1. docs/visibility.md "The occluders'
            faces: returns just outside a tight box".
        surfel_radius_m, surfel_max_px: each occluder return covers a square of
            ``min(surfel_max_px, round(f * r / z))`` pixels either side of its own, r its radius:
            ``surfel_radius_m`` for every return (``surfel_radius_from: fixed``; default 0.02 m
            since 2026-12-02, thirty-fourth session, 0.05 before: a footprint reaches that far
            beyond an occluder's outline, and a tracked point's own window is as wide, so the
            band along every outline where the decision is a footprint's guess narrows with it;
            the closing of ``occluder_fill_px`` fills the gaps between the smaller splats;
            docs/visibility.md "Footprints of 2 cm") or, with
            ``spacing``, ``surfel_spacing_scale`` times the distance to its 4th nearest neighbour
            on the object's surface, within [``surfel_radius_m``, ``surfel_max_radius_m``]
            (:func:`drivetrack.tracks.core.segment_surface_radius`; the clip's returns under
            ``time_model="velocity"`` keep ``surfel_radius_m``).
            Only objects of ``object_types`` and ``occluder_types`` have returns, so only they
            occlude this way.
        surfel_cube_m: side (metres) of the cubes an object's returns over the segment are
            thinned to, one return each (the z-buffer's surface), and whose means the back-face
            normals are fitted on (:func:`drivetrack.tracks.core.segment_surface`). Default 0.025
            (half the footprint of 0.05 m it was tied to before 2026-12-02).
        occluder_recent_types, occluder_recent_frames, occluder_recent_max_m: ``BoxType`` names
            whose objects hide others in an image with their returns of the frames within
            ``occluder_recent_frames`` of that image (every return, not thinned) instead of their
            whole segment's surface, where they are within ``occluder_recent_max_m`` of the
            camera (the median over the clip's images; None: at any distance) and their returns
            over the segment are noisy (their back-face normals were refitted for it, the test
            the segment snap takes; returns that agree keep the segment's surface, bit for bit).
            Default pedestrians, 3 frames either side, 15 m (2026-12-03, fortieth session). A
            walking pedestrian is no rigid body and its few returns register it to its box only
            to centimetres a frame: the segment's returns, carried to one image through the other
            frames' poses, draw it centimetres too wide and hide what passes beside it, while an
            image's near sweeps share that moment's pose. A few sweeps leave open what the lidar
            did not see lately, more so far away. ``()``: every type hides with its segment's
            surface. docs/visibility.md "Pedestrians hide with their recent returns".
        occluder_fill_px: the z-buffer is closed by this many pixels (a grey-level closing,
            nearest depth spread then the farthest taken back: holes up to twice as wide between an
            occluder's splats are filled at its depth, its outlines and depth steps stay where
            they are). The capped footprints of near occluders and the parts of an object no
            lidar sweep sampled leave such holes, through which hidden points were called
            visible. Default 4; 0: off (before 2026-11-26, fifth session; docs/visibility.md).
            Each object's splats are closed on their own, so a gap between two objects stays.
        occluder_subpixels: the z-buffer's resolution, buffer pixels per image pixel along each
            axis (1-4; default 2: outlines placed to half a pixel; 1 before 2026-11-27).
        self_occlusion: the tracked object's own returns are splatted into a z-buffer of their
            own too, so a part of the object in front of another part hides it (a cabin before
            the deck behind it, a near leg before a far one), which neither the back-face test
            nor the other objects' z-buffer sees. Its own surface hides a point only beyond the
            depth the point's own plane spans over a footprint
            (:func:`drivetrack.visibility.zbuffer.own_plane_slack`); needs the back-face test's
            normals (``back_face_max_deg`` set). Default true (since 2026-11-29, twenty-fourth
            session; docs/visibility.md "The object's own surface").
        roof_fill: the other objects' z-buffer surface includes the part of each one's roof its
            returns leave unsampled: the level top of the convex hull of its returns over the
            segment (:func:`drivetrack.visibility.zbuffer.roof_fill`). The lidar sees a car's
            roof at a grazing angle and samples little of it, while a camera a little higher sees
            it as a band above the car's side, hiding what lies behind. Only under
            ``time_model="trajectory"`` (the segment's surface). Default true (since 2026-11-29,
            twenty-fifth session; docs/visibility.md "Roofs the lidar did not sample").
        occluder_hulls: where the z-buffer's footprint rule leaves a point visible although its
            own buffer pixel holds a nearer occluder depth (the band along an occluder's outline,
            and a roof seen at a grazing angle), the ray from the camera to the point decides
            against each other object's convex hull (its segment surface's, moved onto a noisy
            surface, entered by a facet that lies on the surface:
            :func:`drivetrack.visibility.zbuffer.hull_hidden`), at each point's capture time
            under a rolling shutter. Only under ``time_model="trajectory"``. Default true (since
            2026-11-29, twenty-sixth session; docs/visibility.md "Outlines from the occluders'
            hulls").
        occluder_hull_edges: (with ``occluder_hulls``) the other side of that band: where the
            footprint rule hides a point within a buffer pixel of an occluder's outline (the
            window one buffer pixel wider reaches a pixel no occluder covers), the point is
            visible after all when the ray to it misses every other object's convex hull as its
            returns span it (:func:`drivetrack.visibility.zbuffer.hull_missed`). The buffer puts
            an outline to half a pixel; a point a tenth of a pixel above a far car's roof line
            shares the buffer pixel of its topmost returns. Default true (since 2026-12-01,
            thirty-first session; docs/visibility.md "Both sides of the outline band").
        depth_completer, depth_completer_options, depth_batch, depth_lasers, depth_returns,
            see_through_window_deg, see_through_min_quadrants, blind_zone_laser,
            depth_object_motion: the depth
            stage's knobs, see :class:`drivetrack.depth.config.DepthConfig`.
        compensate_sweep_motion: when the scene has ``lidar.capture_offset_s``, select points in
            boxes and compute box-frame points with each box moved to the return's capture time
            (object motion during the LiDAR sweep, :mod:`drivetrack.tracks.sweep_motion`).
        time_model: how an object is placed at each pixel's capture time. ``trajectory``
            (default): its continuous-time trajectory (:mod:`drivetrack.tracks.trajectory`:
            local constant acceleration in world position and yaw through the labels at their
            label times),
            evaluated at the image time (global shutter) or at each point's solved row/column
            time (rolling shutter), and at each LiDAR return's capture time; ``velocity``: the
            box moved along its finite-difference velocity from the frame time to the image pose
            time, returns with constant velocity and yaw rate (before issue 16; for comparison).
        label_time: when a ``lidar_box`` was true: ``frame`` (its frame's timestamp), ``sweep``
            (when the TOP sweep passed its centre) or ``auto`` (default: the convention with the
            smaller residual against the returns, one choice per segment, recorded in
            ``stats/segments.parquet``). Used by ``time_model="trajectory"``.
        label_tilt: the world pitch and roll of an object whose boxes are all yaw-only (labels
            are level in the vehicle frame, so their world tilt is the ego's at that frame):
            ``constant`` (default): the mean over the object's boxes, one tilt per object;
            ``linear``: a straight line in time per object through the ego's tilts (before).
            Only changes of tilt over time move the tracks (docs/time.md). Used by
            ``time_model="trajectory"``; refined 6-DOF boxes keep their own tilt.
        synced_boxes: the segment's ``lidar_camera_synced_box`` boxes are position samples of the
            trajectory too, each at its label's time plus ``t_capture - t_frame`` (its most visible
            camera's capture time of the box centre, solved with that camera's rolling shutter;
            docs/time.md, "Synced boxes"). Default false: by Waymo's definition a synced box is
            its label moved along the labelled speed, which Waymo derives from the same boxes,
            and it measured no better than the trajectory's own fit (bench_time); a producer that
            copies the label box into it would pin movers still. No effect on a segment without
            them. Used by ``time_model="trajectory"``.
        rolling_shutter: project with ``drivetrack.camera.rolling_shutter`` when it is available;
            global-shutter projection at the image pose otherwise.
        max_speed_deviation_mps: if set, drop tracks whose mean world speed deviates from the
            box's annotated mean speed by more than this (paper's remedy for non-rigid parts).
        max_tracks_per_object: if set, keep a seeded random subset of this many candidate points.
        seed: seed of that subset.
        chunk_points: points processed at once (bounds the [T, chunk, 3] float64 temporaries). On
            the numpy path (rolling-shutter cameras, i.e. real ones) a job's peak grows with T x
            chunk_points: measured on a 210-frame clip (docs/benchmarks.md, track stage), 440 MiB
            (tracemalloc) at 8,192, 136 MiB at 2,048 for 55-70% more CPU (each chunk draws its own
            z-buffers); the outputs do not depend on it (the z-buffer's crop holds each point's
            whole-image buffer: ``drivetrack.visibility.zbuffer.crop_growth_px``).
        kernel: inner loop of the global-shutter projection, ``numba`` (fused kernel,
            :mod:`drivetrack.tracks.kernel`) or ``numpy`` (the reference; rolling-shutter cameras
            always use it).
    """
    object_types: tuple[str, ...] = ("VEHICLE",)
    occluder_types: tuple[str, ...] = ("VEHICLE", "PEDESTRIAN", "SIGN", "CYCLIST")
    cameras: tuple[str, ...] = ("FRONT", "FRONT_LEFT", "FRONT_RIGHT")
    lasers: tuple[str, ...] = ("TOP", "FRONT", "SIDE_LEFT", "SIDE_RIGHT", "REAR")
    returns: tuple[int, ...] = (1, 2)
    min_frames: int = 24
    fov_runs: str = "reject"
    fov_samples_per_axis: int = 5
    max_camera_distance_m: float = 20.0
    box_margin_m: float = 0.0
    ground_clearance_m: float = 0.2
    occlusion_ratio: float = 0.95
    depth_lookup_px: int = 1
    depth_lookup_min_jitter_m: float | None = 0.01
    back_face_max_deg: float | None = 90.0
    own_surface_margin_m: float | None = 0.2
    own_surface_max_gap_m: float | None = 1.0
    depth_defers_to_zbuffer: bool = True
    normals_from: str = "segment"
    normal_neighbours: int = 30
    normal_neighbourhood: str = "shifted"
    normal_transfer: str = "ray"
    normal_noise_cubes: float | None = 12.0
    normal_precise_m: float = 0.0005
    box_face_normals_m: float | None = 0.1
    occlusion: str = "surface"
    occluder_tolerance_m: float = 0.15
    occluder_tolerance_rel: float = 0.0
    ambiguity_m: float = 0.1
    ambiguity_deg: float = 5.0
    surfel_radius_m: float = 0.02
    surfel_cube_m: float = 0.025
    surface_snap_max_m: float | None = 0.1
    surface_snap_margin_m: float = 0.1
    surface_snap_segment: bool = True
    segment_margin_m: float | None = None
    surfel_max_px: int = 8
    occluder_fill_px: int = 4
    occluder_recent_types: tuple[str, ...] = ("PEDESTRIAN",)
    occluder_recent_frames: int = 3
    occluder_recent_max_m: float | None = 15.0
    occluder_subpixels: int = 2
    self_occlusion: bool = True
    roof_fill: bool = True
    occluder_hulls: bool = True
    occluder_hull_edges: bool = True
    surfel_radius_from: str = "fixed"
    surfel_spacing_scale: float = 0.6
    surfel_max_radius_m: float = 0.3
    occlusion_margins: bool = False
    # The depth knobs (DepthConfig's fields, in its order; defaults from there).
    depth_completer: str = _DEPTH.depth_completer
    depth_completer_options: dict = field(default_factory=dict, hash=False)
    depth_batch: int = _DEPTH.depth_batch
    depth_lasers: tuple[str, ...] = _DEPTH.depth_lasers
    depth_returns: tuple[int, ...] = _DEPTH.depth_returns
    see_through_window_deg: float | None = _DEPTH.see_through_window_deg
    see_through_min_quadrants: int = _DEPTH.see_through_min_quadrants
    blind_zone_laser: str | None = _DEPTH.blind_zone_laser
    depth_object_motion: bool = _DEPTH.depth_object_motion
    rolling_shutter: bool = True
    compensate_sweep_motion: bool = True
    time_model: str = "trajectory"
    label_time: str = "auto"
    label_tilt: str = "constant"
    synced_boxes: bool = False
    max_speed_deviation_mps: float | None = None
    max_tracks_per_object: int | None = None
    seed: int = 0
    chunk_points: int = 8192
    kernel: str = "numba"

    def __post_init__(self):
        for name, enum_type in (("object_types", BoxType), ("occluder_types", BoxType),
                                ("occluder_recent_types", BoxType), ("cameras", CameraName),
                                ("lasers", LaserName)):
            values = getattr(self, name)
            if isinstance(values, str):
                raise ValueError(f"TrackConfig.{name} must be a sequence of names, got the string {values!r}")
            object.__setattr__(self, name, tuple(values))
            for value in values:
                if value not in enum_type.__members__:
                    raise ValueError(f"TrackConfig.{name}: unknown {enum_type.__name__} {value!r}; "
                                     f"expected one of {sorted(enum_type.__members__)}")
        object.__setattr__(self, "returns", tuple(int(r) for r in self.returns))
        depth = DepthConfig.check({name: getattr(self, name) for name in DEPTH_FIELDS}, where="TrackConfig")
        for name, value in depth.items():
            object.__setattr__(self, name, value)
        if not set(self.returns) <= {1, 2}:
            raise ValueError(f"TrackConfig.returns must be among (1, 2), got {self.returns}")
        if self.fov_runs not in FOV_RUN_POLICIES:
            raise ValueError(f"TrackConfig.fov_runs must be one of {FOV_RUN_POLICIES}, got {self.fov_runs!r}")
        if self.min_frames < 1:
            raise ValueError(f"TrackConfig.min_frames must be >= 1, got {self.min_frames}")
        if self.fov_samples_per_axis < 2:
            raise ValueError(f"TrackConfig.fov_samples_per_axis must be >= 2, got {self.fov_samples_per_axis}")
        if not self.occlusion_ratio > 0:
            raise ValueError(f"TrackConfig.occlusion_ratio must be > 0, got {self.occlusion_ratio}")
        if not (isinstance(self.depth_lookup_px, int) and 0 <= self.depth_lookup_px <= 8):
            raise ValueError(f"TrackConfig.depth_lookup_px must be an integer number of pixels in [0, 8], got "
                             f"{self.depth_lookup_px!r}")
        if self.depth_lookup_min_jitter_m is not None and not self.depth_lookup_min_jitter_m >= 0:
            raise ValueError(f"TrackConfig.depth_lookup_min_jitter_m must be >= 0 metres or None, got "
                             f"{self.depth_lookup_min_jitter_m!r}")
        if self.back_face_max_deg is not None and not 0 < self.back_face_max_deg <= 180:
            raise ValueError(f"TrackConfig.back_face_max_deg must be None or in (0, 180], got "
                             f"{self.back_face_max_deg!r}")
        if self.own_surface_margin_m is not None and not (isinstance(self.own_surface_margin_m, (int, float))
                                                          and 0 <= self.own_surface_margin_m < 10):
            raise ValueError(f"TrackConfig.own_surface_margin_m must be None or a number of metres in [0, 10), "
                             f"got {self.own_surface_margin_m!r}")
        if self.own_surface_max_gap_m is not None and not (isinstance(self.own_surface_max_gap_m, (int, float))
                                                           and self.own_surface_max_gap_m >= 0):
            raise ValueError(f"TrackConfig.own_surface_max_gap_m must be None or a number of metres >= 0, "
                             f"got {self.own_surface_max_gap_m!r}")
        if self.normals_from not in ("segment", "clip"):
            raise ValueError(f"TrackConfig.normals_from must be 'segment' or 'clip', got {self.normals_from!r}")
        if self.box_face_normals_m is not None and not (
                isinstance(self.box_face_normals_m, (int, float)) and 0 <= self.box_face_normals_m < 10):
            raise ValueError(f"TrackConfig.box_face_normals_m must be None or metres in [0, 10), "
                             f"got {self.box_face_normals_m!r}")
        if self.normal_neighbourhood not in NEIGHBOURHOODS:
            raise ValueError(f"TrackConfig.normal_neighbourhood must be 'shifted' or 'centred', "
                             f"got {self.normal_neighbourhood!r}")
        if self.normal_transfer not in NORMAL_TRANSFERS:
            raise ValueError(f"TrackConfig.normal_transfer must be one of {NORMAL_TRANSFERS}, got {self.normal_transfer!r}")
        if not (isinstance(self.normal_precise_m, (int, float)) and not isinstance(self.normal_precise_m, bool)
                and 0 <= self.normal_precise_m <= 0.05):
            raise ValueError(f"TrackConfig.normal_precise_m must be metres in [0, 0.05], got {self.normal_precise_m!r}")
        if self.normal_noise_cubes is not None and not (
                isinstance(self.normal_noise_cubes, (int, float)) and not isinstance(self.normal_noise_cubes, bool)
                and 0 < self.normal_noise_cubes <= 100):
            raise ValueError(f"TrackConfig.normal_noise_cubes must be None or a factor in (0, 100], "
                             f"got {self.normal_noise_cubes!r}")
        if not (isinstance(self.normal_neighbours, int) and self.normal_neighbours >= 3):
            raise ValueError(f"TrackConfig.normal_neighbours must be an integer >= 3, got {self.normal_neighbours!r}")
        if self.occlusion not in OCCLUSION_METHODS:
            raise ValueError(f"TrackConfig.occlusion must be one of {OCCLUSION_METHODS}, got {self.occlusion!r}")
        if not (self.occluder_tolerance_m >= 0 and self.occluder_tolerance_rel >= 0):
            raise ValueError(f"TrackConfig.occluder_tolerance_m and occluder_tolerance_rel must be >= 0, got "
                             f"{self.occluder_tolerance_m!r}, {self.occluder_tolerance_rel!r}")
        if not (self.ambiguity_m >= 0 and 0 <= self.ambiguity_deg <= 90):
            raise ValueError(f"TrackConfig.ambiguity_m must be >= 0 and ambiguity_deg in [0, 90], got "
                             f"{self.ambiguity_m!r}, {self.ambiguity_deg!r}")
        if not (self.surfel_radius_m > 0 and self.surfel_max_px >= 0):
            raise ValueError(f"TrackConfig.surfel_radius_m must be > 0 and surfel_max_px >= 0, got "
                             f"{self.surfel_radius_m!r}, {self.surfel_max_px!r}")
        if not (isinstance(self.surfel_cube_m, (int, float)) and not isinstance(self.surfel_cube_m, bool)
                and 0.001 <= self.surfel_cube_m <= 0.5):
            raise ValueError(f"TrackConfig.surfel_cube_m must be metres in [0.001, 0.5], got {self.surfel_cube_m!r}")
        if self.surface_snap_max_m is not None and not self.surface_snap_max_m > 0:
            raise ValueError(f"TrackConfig.surface_snap_max_m must be None or > 0 metres, got "
                             f"{self.surface_snap_max_m!r}")
        if not self.surface_snap_margin_m >= 0:
            raise ValueError(f"TrackConfig.surface_snap_margin_m must be >= 0 metres, got "
                             f"{self.surface_snap_margin_m!r}")
        if self.segment_margin_m is not None and not (
                isinstance(self.segment_margin_m, (int, float)) and not isinstance(self.segment_margin_m, bool)
                and 0 <= self.segment_margin_m <= 1):
            raise ValueError(f"TrackConfig.segment_margin_m must be None or metres in [0, 1], got "
                             f"{self.segment_margin_m!r}")
        if not isinstance(self.depth_defers_to_zbuffer, bool):
            raise ValueError(f"TrackConfig.depth_defers_to_zbuffer must be true or false, got "
                             f"{self.depth_defers_to_zbuffer!r}")
        if not isinstance(self.self_occlusion, bool):
            raise ValueError(f"TrackConfig.self_occlusion must be true or false, got {self.self_occlusion!r}")
        if not isinstance(self.roof_fill, bool):
            raise ValueError(f"TrackConfig.roof_fill must be true or false, got {self.roof_fill!r}")
        if not isinstance(self.occluder_hulls, bool):
            raise ValueError(f"TrackConfig.occluder_hulls must be true or false, got {self.occluder_hulls!r}")
        if not isinstance(self.occluder_hull_edges, bool):
            raise ValueError(f"TrackConfig.occluder_hull_edges must be true or false, got {self.occluder_hull_edges!r}")
        if not isinstance(self.surface_snap_segment, bool):
            raise ValueError(f"TrackConfig.surface_snap_segment must be true or false, got {self.surface_snap_segment!r}")
        if not (isinstance(self.occluder_subpixels, int) and 1 <= self.occluder_subpixels <= 4):
            raise ValueError(f"TrackConfig.occluder_subpixels must be an integer in [1, 4], got "
                             f"{self.occluder_subpixels!r}")
        if not (isinstance(self.occluder_recent_frames, int) and self.occluder_recent_frames >= 0):
            raise ValueError(f"TrackConfig.occluder_recent_frames must be an integer number of frames >= 0, got "
                             f"{self.occluder_recent_frames!r}")
        if self.occluder_recent_max_m is not None and not self.occluder_recent_max_m > 0:
            raise ValueError(f"TrackConfig.occluder_recent_max_m must be > 0 metres or None, got "
                             f"{self.occluder_recent_max_m!r}")
        if not (isinstance(self.occluder_fill_px, int) and 0 <= self.occluder_fill_px <= 64):
            raise ValueError(f"TrackConfig.occluder_fill_px must be an integer number of pixels in [0, 64], got "
                             f"{self.occluder_fill_px!r}")
        if self.surfel_radius_from not in SURFEL_RADII:
            raise ValueError(f"TrackConfig.surfel_radius_from must be one of {SURFEL_RADII}, got "
                             f"{self.surfel_radius_from!r}")
        if not (self.surfel_spacing_scale > 0 and self.surfel_max_radius_m >= self.surfel_radius_m):
            raise ValueError(f"TrackConfig.surfel_spacing_scale must be > 0 and surfel_max_radius_m >= "
                             f"surfel_radius_m, got {self.surfel_spacing_scale!r}, {self.surfel_max_radius_m!r}")
        from drivetrack.tracks.trajectory import LABEL_TILTS, LABEL_TIMES, TIME_MODELS

        if self.time_model not in TIME_MODELS:
            raise ValueError(f"TrackConfig.time_model must be one of {TIME_MODELS}, got {self.time_model!r}")
        if self.label_time not in LABEL_TIMES:
            raise ValueError(f"TrackConfig.label_time must be one of {LABEL_TIMES}, got {self.label_time!r}")
        if self.label_tilt not in LABEL_TILTS:
            raise ValueError(f"TrackConfig.label_tilt must be one of {LABEL_TILTS}, got {self.label_tilt!r}")
        if self.kernel not in TRACK_KERNELS:
            raise ValueError(f"TrackConfig.kernel must be one of {TRACK_KERNELS}, got {self.kernel!r}")
        if self.chunk_points < 1 or self.depth_batch < 1:
            raise ValueError("TrackConfig.chunk_points and depth_batch must be >= 1")
        if self.max_tracks_per_object is not None and self.max_tracks_per_object < 1:
            raise ValueError(f"TrackConfig.max_tracks_per_object must be >= 1 or None, "
                             f"got {self.max_tracks_per_object}")

    @property
    def object_type_values(self) -> tuple[int, ...]:
        return tuple(int(BoxType[name]) for name in self.object_types)

    @property
    def occluder_recent_type_values(self) -> tuple[int, ...]:
        return tuple(int(BoxType[name]) for name in self.occluder_recent_types)

    @property
    def returns_type_values(self) -> tuple[int, ...]:
        """The ``BoxType`` values whose objects' returns are selected: annotated (``object_types``)
        or occluding (``occluder_types``, under ``occlusion="surface"``)."""
        occluding = self.occluder_types if self.occlusion == "surface" else ()
        return tuple(sorted({int(BoxType[name]) for name in (*self.object_types, *occluding)}))

    @property
    def camera_values(self) -> tuple[int, ...]:
        return tuple(int(CameraName[name]) for name in self.cameras)

    @property
    def laser_values(self) -> tuple[int, ...]:
        return tuple(int(LaserName[name]) for name in self.lasers)

    @property
    def depth_laser_values(self) -> tuple[int, ...]:
        return self.depth.depth_laser_values

    @property
    def depth(self) -> DepthConfig:
        """The depth stage's knobs of this configuration, grouped."""
        return DepthConfig(**{name: getattr(self, name) for name in DEPTH_FIELDS})

    def to_dict(self) -> dict:
        """JSON-ready dict (tuples become lists) for run.json / manifests."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> "TrackConfig":
        """Inverse of :meth:`to_dict`; unknown keys raise, naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"TrackConfig: unknown keys {unknown}")
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in values.items()})
