"""Back faces: which of an object's points turn away from the camera at each frame.

The depth-ratio test (``d_map < occlusion_ratio * z``) cannot see a surface that lies less than
``1 - occlusion_ratio`` of the distance behind another: at 50 m and 0.95 that is 2.5 m, a whole
car, so the far faces of cars seen obliquely were called visible (docs/benchmarks.md, "Visibility
and time on the hard world": 33% of back-face point-frames). Each object's own returns give its
surface: a point whose outward normal points away from the camera is on a face its own object
hides, at any distance.

Normals: PCA over each return's ``k`` nearest neighbours among the object's returns in its box
frame, the clip's or (``cloud``) all of the segment's (``drivetrack.refine.kernel.knn`` /
``normals``, the refinement's estimator), oriented towards the lidar that saw the return (a lidar
sees the outside of a surface), placed by its ``lidar_calibration`` extrinsic
(:func:`sensor_positions`; :data:`SENSOR_VEHICLE_M` where a scene has none), or away from the box
centre where that is the more decisive cue (:func:`orient_outward`: a face the lidar saw at a
grazing angle). The position matters for objects beside the ego: a car 1.5 m away has its roof
below the roof lidar and above a point at bumper height, so one stand-in point for every lidar
turned its roof normals inwards and called the roof a back face. A normal is *unreliable* when
its neighbourhood is too thin to fix a plane: fewer than ``k`` returns, the ``k``-th neighbour
farther than ``max_neighbour_m``, or planarity below ``min_planarity``. An unreliable point on
exactly one face of its label box takes that face's normal (:func:`with_box_face_normals`,
``TrackConfig.box_face_normals_m``); the other unreliable points are never called back faces (the
depth test decides for them).

Own surface in the depth map (:func:`own_surface`): the depth maps are completed from sparse
returns by nearest neighbour in the image, so near an object's own depth edges (a roof seen at a
grazing angle above its rear face, the far end of a side) its own nearer returns are smeared over
its farther, visible points, and the depth-ratio test hid them. A depth-map surface whose point on
the ray to the tracked point lies inside the object's own box (grown by
``TrackConfig.own_surface_margin_m``) is the object itself: whether the object hides its own
point is the back-face test's question, so that surface hides nothing at a point whose normal is
reliable (where it is not, the back-face test cannot decide: there the surface is the object's
own only where the ray from it to the point runs outside the box itself).

Returns onto their surface (:func:`points_on_surface`, ``TrackConfig.surface_snap_max_m``): a
return's range carries centimetres of noise along its ray, and a tracked point carries that offset
through every frame (at a few metres from a camera a centimetre across its ray is pixels). The
returns of the object's own sweep and the nearest few round it, on the same face, give the
surface under it far better; the point moves along its own ray onto it, when the returns show
range noise at all (exact ranges stay bit for bit).

Shapes: n points, T frames; metres, box frame unless named otherwise.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

__all__ = ["NEIGHBOURHOODS", "OWN_BOX_DEPTH_M", "SENSOR_VEHICLE_M", "SHIFT_MAX_TILT_DEG", "SHIFT_SIGMAS",
           "SHIFT_TIGHT_M", "SHIFT_TOLERANCE_M", "SOLID_FACE_MAX_M", "CloudNormals", "SurfaceCloud", "SurfelNormals",
           "box_face_normals",
           "camera_centres_box", "cloud_normals", "facing_cosine", "facing_mask", "facing_test", "orient_outward",
           "facing_test_towards",
           "other_boxes", "other_surface", "solid_extents", "own_box_parameters", "own_surface", "points_on_surface",
           "points_on_sweep_surface", "range_noise_m", "sensor_positions", "surface_cloud", "surfel_normals",
           "with_box_face_normals"]

#: Stand-in lidar position (vehicle frame, metres) for a laser without calibration: about where
#: Waymo's roof lidar sits (1.4 m ahead of the rear axle, 2.2 m up).
SENSOR_VEHICLE_M = np.array([1.4, 0.0, 2.2])


def sensor_positions(lasers: np.ndarray, origins: dict[int, np.ndarray]) -> np.ndarray:
    """float64 [n, 3]: the vehicle-frame position of the lidar of each return.

    ``lasers`` int [n] (``LaserName`` values), ``origins`` laser -> float64 [3] (``Scene.lidar_origins``).
    """
    table = np.tile(SENSOR_VEHICLE_M, (8, 1))
    for laser, origin in origins.items():
        if 0 <= int(laser) < table.shape[0]:
            table[int(laser)] = origin
    return table[np.asarray(lasers, dtype=np.int64)]


@dataclass
class SurfelNormals:
    """Per-point surface normals of one object.

    Attributes:
        normal: float64 [n, 3], unit, box frame, outward (towards the sensor side).
        reliable: bool [n], whether the neighbourhood fixes a plane (see the module docstring).
    """
    normal: np.ndarray
    reliable: np.ndarray

    @property
    def num_unreliable(self) -> int:
        return int((~self.reliable).sum())


#: A neighbourhood's plane passes through a point (so its normal may be the point's,
#: :func:`cloud_normals`) when the point lies within this distance of it (metres) ...
SHIFT_TOLERANCE_M = 0.01
#: ... or within this many standard deviations of the neighbourhood's own spread about its plane
#: (``sqrt(l1)``: range noise, a curved surface).
SHIFT_SIGMAS = 3.0
#: ... and whose normal lies within this angle (degrees) of the point's own neighbourhood's.
SHIFT_MAX_TILT_DEG = 45.0
#: :func:`cloud_normals`' second pass (``TrackConfig.normal_precise_m``'s default): a point whose
#: chosen plane misses it by more than this (metres) or :data:`SHIFT_SIGMAS` times that plane's own
#: spread, or is no precise plane through it (spread and miss both within this), may lie on
#: another face: it takes the flattest of its neighbours' chosen planes that passes that close.
SHIFT_TIGHT_M = 0.0005
NEIGHBOURHOODS = ("shifted", "centred")
#: :meth:`CloudNormals.on_plane`: a point takes the normal of the one of this many cloud points
#: (its nearest cloud point's nearest, itself included) whose plane passes nearest it.
PLANE_CANDIDATES = 12
#: ... when its nearest cloud point's plane misses it by more than this (metres); closer, it keeps
#: the nearest's (the same face: the cost of the search is spent near edges and on noisy returns).
PLANE_GATE_M = 0.0005
#: :func:`surfel_normals`: how a point takes a normal from the cloud's (``nearest`` cloud point,
#: the cloud point whose plane passes nearest it among the nearest few, ``plane``, or, where the
#: returns carry range noise, the plane its lidar ray enters the surface by among those, ``ray``).
NORMAL_TRANSFERS = ("nearest", "plane", "ray")
#: :meth:`CloudNormals.on_ray`: candidate planes within this angle (degrees) of each other are one
#: face (their offsets are pooled) ...
RAY_FACE_DEG = 30.0
#: ... a plane faces the lidar when the ray meets it more steeply than this cosine (0: at all) ...
RAY_MIN_COS = 0.0
#: ... and is a candidate only where the ray meets it within this distance (metres) of the return
#: (centimetres of range noise, decimetre cubes) ...
RAY_MAX_STEP_M = 0.1
#: ... and an edge is concave (a bonnet meeting a windscreen: the ray enters by the first plane,
#: not the last) where the other face's points lie beyond this (metres) towards the outside of
#: the face entered last, by ``(c_other - c_last) . (n_last - n_other)`` (:meth:`CloudNormals.on_ray`).
RAY_CONCAVE_M = 0.005
#: Points per block of :meth:`CloudNormals.on_ray`'s [b, k, k] arrays (2,048: a few MiB each).
RAY_BLOCK = 2048


@dataclass
class CloudNormals:
    """Unoriented normals of an object's point cloud, one per cloud point (:func:`cloud_normals`).

    Attributes:
        cloud: float64 [m, 3], the points (box frame, metres).
        normal: float64 [m, 3], unit, sign arbitrary.
        planarity: float64 [m], ``(l2 - l1) / l3`` of the neighbourhood the normal is from.
        reach_m: float64 [m], that neighbourhood's k-th neighbour's distance from its centre
            point (metres).
    """
    cloud: np.ndarray
    normal: np.ndarray
    planarity: np.ndarray
    reach_m: np.ndarray
    #: the search structure of :meth:`nearest`, built on its first call
    _tree: object = field(default=None, repr=False, compare=False)
    #: int64 [m, k] or None: each cloud point's nearest cloud points (itself first), the
    #: candidates of :meth:`on_plane`
    neighbours: np.ndarray | None = field(default=None, repr=False, compare=False)
    #: the side (metres) of the coarse cubes :func:`noise_aware_normals` refitted the normals on
    #: because the returns carry range noise; None: the fine cloud's (no noise found)
    noise_cube_m: float | None = None

    def nearest(self, points: np.ndarray) -> np.ndarray:
        """int64 [n]: the index of the cloud point nearest each of ``points`` float [n, 3] (finite;
        box frame, metres), exactly ``scipy.spatial.cKDTree(cloud).query(points, k=1)``'s.

        With numba, a grid over the cloud (:func:`~drivetrack.visibility.kernel.cloud_grid`,
        :func:`~drivetrack.visibility.kernel.nearest_in_grid`: the same squared distances, ties
        between exactly equidistant cloud points to the lower index; on the object's own returns,
        about a fifth of the tree's time); without it (or for an empty cloud), the tree itself.
        """
        from drivetrack.visibility import kernel

        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if kernel.NUMBA_AVAILABLE and self.cloud.shape[0]:
            if not isinstance(self._tree, kernel.CloudGrid):
                self._tree = kernel.cloud_grid(self.cloud, kernel.grid_cell(self.cloud))
            return kernel.nearest_in_grid(self._tree, points)
        from scipy.spatial import cKDTree

        if not isinstance(self._tree, cKDTree):
            self._tree = cKDTree(self.cloud)
        return np.asarray(self._tree.query(points, k=1)[1], dtype=np.int64).reshape(-1)

    def on_plane(self, points: np.ndarray, candidates: int = PLANE_CANDIDATES,
                 nearest: np.ndarray | None = None) -> np.ndarray:
        """int64 [n]: for each of ``points`` float [n, 3] (finite; box frame, metres), the cloud
        point whose plane (through it, with its normal) passes nearest the point, among the
        ``candidates`` nearest cloud points of its own nearest cloud point (:meth:`nearest`; itself
        included), when the nearest's plane misses the point by more than :data:`PLANE_GATE_M`;
        ties to the nearer in that order.

        Why not the nearest cloud point's normal alone: the cloud is the means of 2.5 cm cubes, so
        a point within a cube's width of an edge often has its nearest cloud point on the other
        face (or the cube astride the edge) and took that face's normal: on a box car's back face
        1 cm from a face that sees the camera, the back face was called visible
        (docs/visibility.md, "Normals near an edge"). Its own face's cloud points' planes pass
        through it; the other face's miss it by its distance from the edge."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        nearest = self.nearest(points) if nearest is None else np.array(nearest, dtype=np.int64)
        k = 0 if self.neighbours is None else min(int(candidates), self.neighbours.shape[1])
        if k <= 1 or points.shape[0] == 0:
            return nearest
        gap = np.abs(np.einsum("nj,nj->n", self.normal[nearest], points - self.cloud[nearest]))
        redo = np.flatnonzero(gap > PLANE_GATE_M)
        index = self.neighbours[nearest[redo], :k]                                    # [r, k]
        gaps = np.abs(np.einsum("nkj,nkj->nk", self.normal[index], points[redo, None, :] - self.cloud[index]))
        nearest[redo] = index[np.arange(redo.size), np.argmin(gaps, axis=1)]
        return nearest

    def on_ray(self, points: np.ndarray, sensors: np.ndarray, centre: np.ndarray | None = None,
               candidates: int = PLANE_CANDIDATES) -> np.ndarray:
        """int64 [n]: for each of ``points`` float [n, 3] (finite; box frame, metres), seen by the
        lidar at ``sensors`` float [n, 3] (box frame), the cloud point of the face its ray enters the
        surface by, among the ``candidates`` nearest cloud points of its own nearest cloud point
        (as :meth:`on_plane`; a point on its nearest's plane, within :data:`PLANE_GATE_M`, keeps
        it).

        Range noise moves a return along its ray, never across it: near an edge it may lie
        centimetres off both faces' planes, and which plane passes nearest it (:meth:`on_plane`) is
        the noise's choice (a return 1-2 cm from an edge took the other face's normal about a
        third of the time under 2 cm of noise). The ray itself is exact. Each candidate's plane
        (its normal, the offset the median of its face's candidates, those within
        :data:`RAY_FACE_DEG`: the noise of one cloud point averaged out) is turned outward
        (:func:`orient_outward`, the box centre ``centre``, default the origin, or the sensor) and
        met by the ray at a signed step from the return; a plane the lidar sees (facing its ray,
        cosine below -:data:`RAY_MIN_COS`) met within :data:`RAY_MAX_STEP_M` is a candidate. A solid's
        convex edge is entered by the plane the ray meets *last* (the solid is the intersection
        of the faces' half-spaces): that one, unless the edge is concave (the union of the
        half-spaces: entered by the first), where the other faces' cloud points ``c`` lie towards
        the outside of the last face and its points (their mean ``c_last``) towards theirs, a
        median ``(c - c_last) . (n_last - n)`` over :data:`RAY_CONCAVE_M` (positions decimetres
        apart, where a face's offset is centimetres off). Without a candidate, :meth:`on_plane`'s
        choice.
        """
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        sensors = np.broadcast_to(np.asarray(sensors, dtype=np.float64), points.shape)
        nearest = self.nearest(points)
        at = self.on_plane(points, candidates, nearest=nearest)       # kept where the ray cannot say
        k = 0 if self.neighbours is None else min(int(candidates), self.neighbours.shape[1])
        if k <= 1 or points.shape[0] == 0:
            return at
        gap = np.abs(np.einsum("nj,nj->n", self.normal[nearest], points - self.cloud[nearest]))
        redo = np.flatnonzero(gap > PLANE_GATE_M)
        same_cos = np.cos(np.radians(RAY_FACE_DEG))
        if redo.size:
            # all candidates on one face (within RAY_FACE_DEG of the first, signs aside): no edge to
            # enter by, on_plane's choice (the plane passing nearest)
            normal = self.normal[self.neighbours[nearest[redo], :k]]
            redo = redo[~(np.abs(np.einsum("rkj,rj->rk", normal, normal[:, 0])) >= same_cos).all(axis=1)]
            del normal
        origin = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
        for start in range(0, redo.size, RAY_BLOCK):
            rows = redo[start:start + RAY_BLOCK]
            b, line = rows.size, np.arange(rows.size)
            index = self.neighbours[nearest[rows], :k]                                       # [b, k]
            cloud = self.cloud[index]                                                         # [b, k, 3]
            normal = self.normal[index]
            # outward, by the more decisive of the sensor and the centre (orient_outward)
            flip = orient_outward(normal.reshape(-1, 3), (cloud - origin).reshape(-1, 3),
                                  np.repeat(sensors[rows] - origin, k, axis=0)).reshape(b, k)
            normal = np.where(flip[..., None], -normal, normal)
            same = np.abs(np.einsum("bkj,blj->bkl", normal, normal)) >= same_cos              # [b, k, k]
            offset = _masked_median(np.einsum("bkj,blj->bkl", normal, cloud), same)             # [b, k]
            ray = points[rows] - sensors[rows]
            ray /= np.maximum(np.linalg.norm(ray, axis=1, keepdims=True), 1e-12)
            cos = np.einsum("bkj,bj->bk", normal, ray)                                       # < 0: facing
            with np.errstate(divide="ignore", invalid="ignore"):
                step = (offset - np.einsum("bkj,bj->bk", normal, points[rows])) / cos        # [b, k]
            ok = (cos < -RAY_MIN_COS) & (np.abs(step) <= RAY_MAX_STEP_M)
            last = np.argmax(np.where(ok, step, -np.inf), axis=1)
            first = np.argmin(np.where(ok, step, np.inf), axis=1)
            # concave: the other faces' points lie towards the last face's outside, its points towards
            # theirs: (c_other - c_last) . (n_last - n_other) > 0 (a convex edge: < 0), with c_last
            # the mean of the last face's candidates (decimetres apart, not the offsets' centimetres)
            mine = same[line, last] & ok
            centre_last = np.einsum("bk,bkj->bj", mine, cloud) / np.maximum(mine.sum(axis=1), 1)[:, None]
            opening = np.einsum("bkj,bkj->bk", cloud - centre_last[:, None, :], normal[line, last][:, None, :] - normal)
            other = ok & ~same[line, last]
            some = np.flatnonzero(other.any(axis=1))
            concave = np.zeros(b, dtype=bool)
            if some.size:
                concave[some] = _masked_median(opening[some], other[some]) > RAY_CONCAVE_M
            found = ok.any(axis=1)
            at[rows[found]] = index[line[found], np.where(concave, first, last)[found]]
        return at


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """float64 [...]: the median along the last axis of ``values`` float [..., k] where ``mask``
    bool [..., k] (every row has at least one), as ``np.nanmedian`` of the others set to NaN (the
    mean of the two middle values of an even count), by one sort: nanmedian's per-row selection is
    ten times slower on small rows."""
    ordered = np.sort(np.where(mask, values, np.inf), axis=-1)
    count = mask.sum(axis=-1, keepdims=True)
    low = np.take_along_axis(ordered, (count - 1) // 2, axis=-1)
    high = np.take_along_axis(ordered, count // 2, axis=-1)
    return (0.5 * (low + high))[..., 0]


#: :func:`noise_aware_normals`: the normals' cubes are never coarser than this (metres) ...
NOISY_CUBE_MAX_M = 0.12
#: ... and are coarsened only when that makes them at least this many times the fine cubes' side.
NOISY_CUBE_MIN_GAIN = 1.5


def surface_spread_m(fitted: CloudNormals) -> float:
    """The spread (metres) of an object's cloud about its own fitted planes: the median, over
    every cloud point and its nearest :data:`PLANE_CANDIDATES` - 1 other cloud points, of their
    distance from its plane. 0 for returns on flat faces (a box car's with exact ranges); under
    range noise centimetres (2 cm noise on the medium hard world with 5 cm labels: 6-15 mm)."""
    if fitted.neighbours is None or fitted.cloud.shape[0] == 0 or fitted.neighbours.shape[1] < 2:
        return 0.0
    index = fitted.neighbours
    gaps = np.abs(np.einsum("nkj,nj->nk", fitted.cloud[index] - fitted.cloud[:, None, :], fitted.normal))
    return float(np.median(gaps[:, 1:]))


def noise_aware_normals(fine: np.ndarray, cube_m: float, neighbours: int, neighbourhood: str = "shifted",
                        noise_cubes: float | None = None,
                        returns_of: Callable[[], np.ndarray] | None = None,
                        precise_m: float | None = None) -> CloudNormals | None:
    """The back-face normals of an object: :func:`cloud_normals` of ``fine`` float64 [k, 3], the
    means of its returns in cubes of side ``cube_m`` (box frame, metres), or of coarser cubes'
    means where the returns carry range noise.

    Range noise moves each return along its ray by centimetres, so the fine cubes' means stack in
    a slab several cubes thick, and a neighbourhood of ``neighbours`` of them spans a few
    centimetres along the surface: its plane is the noise's (on the medium hard world with 5 cm
    labels and 2 cm range noise, 2% of a close car's reliable normals pointed into it and 9% more
    were tilted over 45 degrees; exact ranges: 0.01% / 0.1%). With ``noise_cubes`` set, the
    spread of the fine cloud about its planes (:func:`surface_spread_m`) times ``noise_cubes``,
    at most :data:`NOISY_CUBE_MAX_M`, is the side of the cubes the normals are fitted on when it
    is at least :data:`NOISY_CUBE_MIN_GAIN` times ``cube_m``; their means are those of the
    returns ``returns_of()`` float64 [m, 3] (called only then): each coarse cube's mean averages
    the noise of many returns, and its neighbourhood spans decimetres. Returns on flat faces with
    exact ranges have no spread and keep the fine cubes' normals bit for bit. None when ``fine``
    has fewer than ``neighbours`` points (as :func:`cloud_normals`, which takes ``precise_m``)."""
    from drivetrack.visibility.zbuffer import surfel_means

    fitted = cloud_normals(fine, neighbours, neighbourhood, precise_m)
    if fitted is None or noise_cubes is None or returns_of is None:
        return fitted
    coarse_m = min(float(noise_cubes) * surface_spread_m(fitted), NOISY_CUBE_MAX_M)
    if coarse_m < NOISY_CUBE_MIN_GAIN * cube_m:
        return fitted
    coarse = cloud_normals(surfel_means(np.ascontiguousarray(returns_of(), dtype=np.float64), coarse_m), neighbours,
                           neighbourhood, precise_m)
    if coarse is None:
        return fitted
    coarse.noise_cube_m = coarse_m
    return coarse


def cloud_normals(cloud: np.ndarray, neighbours: int, neighbourhood: str = "shifted",
                  precise_m: float | None = None) -> CloudNormals | None:
    """PCA normals of every point of ``cloud`` float64 [m, 3] (box frame) from ``neighbours``
    nearest points (itself included; ``drivetrack.refine.kernel``'s estimator); None when the
    cloud has fewer than ``neighbours`` points.

    ``centred``: each point's own neighbourhood. Near a sharp edge it straddles both faces and
    its plane cuts the corner (45 degrees off at a box's edge): a point on a car's side a few
    centimetres from its front, seen from ahead at a grazing angle, got a normal that faces the
    camera, and its back face was called visible (docs/visibility.md "Shifted neighbourhoods").
    ``shifted``: each point takes, among the neighbourhoods of its own neighbours (its own
    included) whose plane passes through it (within :data:`SHIFT_TOLERANCE_M`, or
    :data:`SHIFT_SIGMAS` times the neighbourhood's spread about its plane) and whose normal lies
    within :data:`SHIFT_MAX_TILT_DEG` of its own neighbourhood's, the flattest: the smallest
    surface variation ``l1 / (l1 + l2 + l3)``. Near an edge that is a neighbourhood lying on the
    point's own face (its own neighbourhood, mostly on that face, leans that way: the tilt limit
    keeps a flat neighbourhood of the other face, whose plane passes within the noise of a point
    near the edge, from being taken); on a flat face or a smooth surface every candidate gives
    about the same normal; the more neighbours, the farther from an edge the shift reaches.
    A second pass (``precise_m``, default :data:`SHIFT_TIGHT_M`; 0: none) gives a point whose
    chosen plane misses it beyond that plane's spread, or is no precise plane through it, the
    flattest of its neighbours' chosen planes (of any tilt) that passes through it that closely:
    the top scan line of a sparsely sampled face just under a densely sampled one leaned the dense
    face's way and took its plane (docs/visibility.md "Planes that pass through their points")."""
    from drivetrack.refine.kernel import knn, plane_fits
    from drivetrack.visibility.kernel import shifted_neighbourhoods

    if neighbourhood not in NEIGHBOURHOODS:
        raise ValueError(f"cloud_normals: neighbourhood must be one of {NEIGHBOURHOODS}, got {neighbourhood!r}")
    cloud = np.ascontiguousarray(cloud, dtype=np.float64)
    if cloud.shape[0] < max(neighbours, 1):
        return None
    dist, index = knn(cloud, neighbours)
    normal, planarity, centroid, eigen = plane_fits(cloud, index)
    choice = np.arange(cloud.shape[0])
    if neighbourhood == "shifted":
        tight_m = SHIFT_TIGHT_M if precise_m is None else float(precise_m)
        choice = shifted_neighbourhoods(cloud, index, normal, centroid, eigen, SHIFT_TOLERANCE_M, SHIFT_SIGMAS,
                                        SHIFT_MAX_TILT_DEG, tight_m)
    return CloudNormals(cloud, normal[choice], planarity[choice], dist[choice, -1],
                        neighbours=np.ascontiguousarray(index[:, :PLANE_CANDIDATES], dtype=np.int64))


def surfel_normals(points_box: np.ndarray, sensor_box: np.ndarray, neighbours: int = 12,
                   max_neighbour_m: float = 0.5, min_planarity: float = 0.2,
                   cloud: np.ndarray | None = None, neighbourhood: str = "shifted",
                   fitted: CloudNormals | None = None, transfer: str = "nearest",
                   precise_m: float | None = None) -> SurfelNormals:
    """Normals of every point float64 [n, 3] of one object, from its own point cloud.

    Args:
        points_box: float64 [n, 3], the object's returns in its box frame (all clip frames).
        sensor_box: float64 [n, 3], the sensor position of each return's frame, in the box frame
            of that frame (normals are turned to face it, or away from the box centre where
            that is the more decisive cue: :func:`orient_outward`).
        neighbours: k of the k-nearest-neighbour PCA.
        max_neighbour_m: the k-th neighbour must lie within this distance.
        min_planarity: smallest ``(l2 - l1) / l3`` of the neighbourhood's covariance.
        cloud: float64 [m, 3], box frame: the normals are those of these points (the object's
            returns over the whole segment, :func:`drivetrack.tracks.core.segment_normals_cloud`),
            each point taking its nearest cloud point's, instead of those of ``points_box`` itself.
        neighbourhood: ``shifted`` or ``centred`` (:func:`cloud_normals`).
        fitted: :func:`cloud_normals` of ``cloud`` (or of ``points_box``) computed before (an
            object seen by several cameras); ``cloud``, ``neighbours`` and ``neighbourhood`` are
            then not used.
        transfer: with ``cloud`` or ``fitted``, how each point takes a cloud point's normal
            (:data:`NORMAL_TRANSFERS`): ``nearest`` (:meth:`CloudNormals.nearest`), ``plane``
            (:meth:`CloudNormals.on_plane`: right at an edge with exact ranges) or ``ray`` (the
            track stage's back-face normals): where ``fitted`` was refitted for range noise
            (``noise_cube_m``, :func:`noise_aware_normals`) the face the point's ray from
            ``sensor_box`` enters by (:meth:`CloudNormals.on_ray`), elsewhere ``plane``'s.
        precise_m: :func:`cloud_normals`' second pass (without ``fitted``).
    """
    if transfer not in NORMAL_TRANSFERS:
        raise ValueError(f"surfel_normals: transfer must be one of {NORMAL_TRANSFERS}, got {transfer!r}")
    points_box = np.ascontiguousarray(points_box, dtype=np.float64)
    n = points_box.shape[0]
    own = cloud is None and fitted is None
    if fitted is None:
        fitted = cloud_normals(points_box if cloud is None else cloud, neighbours, neighbourhood, precise_m)
    if fitted is None:
        return SurfelNormals(np.zeros((n, 3)), np.zeros(n, dtype=bool))
    at = (np.arange(n) if own else fitted.on_plane(points_box) if transfer == "plane"
          else (fitted.on_ray(points_box, sensor_box) if fitted.noise_cube_m is not None else fitted.on_plane(points_box))
          if transfer == "ray" else fitted.nearest(points_box))
    normal = fitted.normal[at]
    normal[orient_outward(normal, points_box, sensor_box)] *= -1.0
    reliable = (fitted.reach_m[at] <= max_neighbour_m) & (fitted.planarity[at] >= min_planarity)
    return SurfelNormals(normal, reliable)


#: :func:`points_on_surface`: the surface under a point is the mean of the returns within this
#: distance (metres) of its normal line ...
SNAP_RADIUS_M = 0.08
#: ... and this distance of the point along it (metres; a range's noise is centimetres) ...
SNAP_SLAB_M = 0.08
#: ... whose normal lies within this angle (degrees) of the point's (the same face) ...
SNAP_MAX_TILT_DEG = 30.0
#: ... when there are at least this many of them.
SNAP_MIN_RETURNS = 10
#: A point moves only when its ray meets the surface at least this steeply (the cosine between
#: ray and normal): at grazing incidence a small error of the surface is a long move along the ray.
SNAP_MIN_INCIDENCE_COS = 0.1
#: ... and only when the returns' range noise (:func:`range_noise_m`) is at least this (metres):
#: exact ranges stay where they are ...
SNAP_MIN_NOISE_M = 0.002
#: ... estimated from at least this many returns, of an even subset of this many at most from
#: this many of the clip's frames (evenly spaced).
SNAP_MIN_POINTS = 100
SNAP_NOISE_SAMPLE = 2000
SNAP_NOISE_FRAMES = 4
#: The surface under a return is that of the returns of its own sweep and of this many sweeps before
#: and after it (placed by the object's trajectory: more returns, their placement's errors small).
SNAP_WINDOW_FRAMES = 2


@dataclass
class SurfaceCloud:
    """An object's returns over the segment, frame by frame, for :func:`points_on_surface`.

    Attributes:
        points: float64 [r, 3], the returns (box frame at each one's capture time, metres), sorted
            by frame.
        normal: float64 [r, 3], unit, each one's normal (its nearest back-face cloud point's; sign
            arbitrary).
        frames: int64 [F], the segment frames that have returns, ascending.
        offsets: int64 [F + 1], the returns of ``frames[i]`` are rows ``offsets[i]:offsets[i + 1]``.
        remembered: ``(keys int64 [m] ascending, steps float64 [m])``: the steps to the surface
            (metres, along the ray; NaN: none) of the points already moved, by their keys
            (:func:`points_on_surface`'s ``keys``): an object seen by several cameras has the
            same returns in each camera's clip, and each is measured once.
    """
    points: np.ndarray
    normal: np.ndarray
    frames: np.ndarray
    offsets: np.ndarray
    remembered: tuple = field(default_factory=lambda: (np.zeros(0, dtype=np.int64), np.zeros(0)),
                              repr=False, compare=False)


def surface_cloud(points_box: np.ndarray, frame: np.ndarray, fitted: CloudNormals) -> SurfaceCloud:
    """The :class:`SurfaceCloud` of an object's returns ``points_box`` float64 [r, 3] (box frame;
    selected from the label boxes *grown* by a few centimetres: see :func:`points_on_surface`),
    ``frame`` int [r] each one's segment frame; ``fitted`` the back-face normals' cloud."""
    normal = fitted.normal[fitted.nearest(points_box)] if points_box.shape[0] else np.zeros((0, 3))
    return SurfaceCloud(*_by_frame(points_box, normal, frame))


def range_noise_m(steps: np.ndarray) -> float:
    """The returns' range noise (metres, a sigma) from ``steps`` float [n] (metres), each
    return's distance along its ray from the surface under it (:func:`points_on_surface`): 1.4826
    times their median absolute value (the median absolute deviation of a normal distribution);
    NaN for none."""
    steps = np.asarray(steps, dtype=np.float64)
    return float(1.4826 * np.median(np.abs(steps))) if steps.size else float("nan")


def points_on_surface(points_box: np.ndarray, frame: np.ndarray, rays_box: np.ndarray, normal: np.ndarray,
                      surface, usable: np.ndarray, max_move_m: float,
                      keys: np.ndarray | None = None, window: int = SNAP_WINDOW_FRAMES,
                      radius_m: float = SNAP_RADIUS_M, min_returns: int = SNAP_MIN_RETURNS,
                      min_noise_m: float = SNAP_MIN_NOISE_M) -> tuple[np.ndarray, np.ndarray]:
    """Each return moved along its own lidar ray onto the object's surface: ``(moved float64 [n,
    3], moved bool [n])``.

    A return's range carries centimetres of noise, along its ray; the surface under it is known
    far better from the many returns round it, of its own sweep and the nearest few.
    ``points_box`` float64 [n, 3], ``frame`` int [n] each one's segment frame and ``rays_box``
    float64 [n, 3] (each ray's direction, any length) in the box frame, ``normal`` float64 [n, 3]
    each point's unit normal (sign arbitrary); ``surface`` the object's returns frame by frame
    (:func:`surface_cloud`; or a function of no arguments returning it or None, called only when
    the returns are moved); ``usable`` bool [n]: the points whose normal is reliable; ``keys`` int
    [n] or None: each point's unique id (its lidar row), under which its step to the surface is
    remembered in ``surface`` (:attr:`SurfaceCloud.remembered`) for later calls with the same
    points, positions and normals (an object's clips in several cameras); ``window``: the frames
    either side whose returns make the surface (:data:`SNAP_WINDOW_FRAMES`; 0: the point's own
    sweep alone, which needs no poses between sweeps: :func:`points_on_sweep_surface`);
    ``radius_m`` and ``min_returns``: the cylinder's radius and the returns it must hold
    (:data:`SNAP_RADIUS_M`, :data:`SNAP_MIN_RETURNS`); ``min_noise_m`` the range noise that moves
    them (:data:`SNAP_MIN_NOISE_M`).

    The surface under a point is the mean, along its normal, of the returns of its frame and
    :data:`SNAP_WINDOW_FRAMES` frames either side within :data:`SNAP_RADIUS_M` of its normal line
    and :data:`SNAP_SLAB_M` along it whose normal lies within :data:`SNAP_MAX_TILT_DEG` of it
    (:func:`drivetrack.visibility.kernel.surface_offsets`; at least :data:`SNAP_MIN_RETURNS`). The
    point moves to where its ray meets that plane when the ray meets it at
    :data:`SNAP_MIN_INCIDENCE_COS` or steeper and the move is at most ``max_move_m`` (metres); the
    others stay. Only a few sweeps either side: over a whole segment the trajectory's errors
    (label noise) would add up.

    Nothing moves unless the returns show range noise: :func:`range_noise_m` of an even subset of
    :data:`SNAP_NOISE_SAMPLE` of the points on :data:`SNAP_NOISE_FRAMES` frames, measured against
    the surface of the points themselves (of those frames and their neighbours; at least
    :data:`SNAP_MIN_POINTS` of them), must be :data:`SNAP_MIN_NOISE_M` or more. The points are the
    returns inside the box, so that is about half the noise: a detection, not an estimate. Exact
    ranges stay bit for bit (the returns of other sweeps are placed by the object's trajectory,
    and a surface drawn from them would move an exact return by that placement's millimetres).

    ``surface`` must hold the returns on *both* sides of the surface: a selection that keeps only
    the returns inside the label box keeps those whose noise moved them inwards where the box is
    tight, and their mean lies inside the true surface.
    """
    points_box = np.ascontiguousarray(points_box, dtype=np.float64)
    frame = np.asarray(frame, dtype=np.int64)
    ray = rays_box / np.linalg.norm(rays_box, axis=1, keepdims=True)
    incidence = np.einsum("ni,ni->n", ray, normal)
    candidates = np.flatnonzero(usable & (np.abs(incidence) >= SNAP_MIN_INCIDENCE_COS))
    out, moved = points_box.copy(), np.zeros(points_box.shape[0], dtype=bool)
    # the noise first, from an even subset of a few frames (exact ranges: nothing more to do)
    some = _noise_frames(frame[candidates])
    subset = candidates[np.isin(frame[candidates], some)]
    subset = subset[np.unique(np.linspace(0, subset.size - 1, min(subset.size, SNAP_NOISE_SAMPLE)).astype(np.int64))]
    # the returns within ``window`` frames of those (frame numbers are integers)
    near_some = np.isin(frame, (some[:, None] + np.arange(-window, window + 1)[None, :]).ravel())
    own = SurfaceCloud(*_by_frame(points_box[near_some], normal[near_some], frame[near_some]))
    step = _steps_to_surface(points_box, frame, incidence, normal, own, subset, window, radius_m, min_returns)
    ok = np.isfinite(step) & (np.abs(step) <= max_move_m)
    if ok.sum() < min(SNAP_MIN_POINTS, SNAP_NOISE_SAMPLE) or not range_noise_m(step[ok]) >= min_noise_m:
        return out, moved
    surface = surface() if callable(surface) else surface
    if surface is None:
        return out, moved
    if keys is None:
        step = _steps_to_surface(points_box, frame, incidence, normal, surface, candidates, window, radius_m,
                                 min_returns)
    else:
        step = _remembered_steps(surface, np.asarray(keys, dtype=np.int64)[candidates], lambda missing: _steps_to_surface(
            points_box, frame, incidence, normal, surface, candidates[missing], window, radius_m, min_returns))
    ok = np.isfinite(step) & (np.abs(step) <= max_move_m)
    rows = candidates[ok]
    out[rows] += step[ok, None] * ray[rows]
    moved[rows] = True
    return out, moved


#: :func:`points_on_sweep_surface`: the neighbours of a sweep's PCA normals (reliable as
#: :func:`surfel_normals` takes them)
SWEEP_NORMAL_NEIGHBOURS = 12
#: :func:`points_on_sweep_surface`: one sweep holds a fifth of the returns of five, so the
#: cylinder is wider than :data:`SNAP_RADIUS_M` and needs fewer of them
SWEEP_RADIUS_M = 0.1
SWEEP_MIN_RETURNS = 6
#: :func:`points_on_sweep_surface`'s range-noise detection (metres): its candidates hold both
#: sides of the surface, so it sees the whole noise (2 cm: 17-21 mm measured), and one sweep's
#: surface bends more with the object (exact ranges: 0.1-1.9 mm on the medium hard world's
#: movers, 5.4 mm on a small world's pedestrian from 239 returns)
SWEEP_MIN_NOISE_M = 0.008


def points_on_sweep_surface(points: np.ndarray, frame: np.ndarray, sensor: np.ndarray, max_move_m: float,
                            rows: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Returns ``rows`` of an object's returns each moved along its own ray onto the surface of
    its own sweep's returns round it: ``(moved float64 [k, 3], moved bool [k])``; nothing moves
    unless the returns show range noise (:func:`points_on_surface` with ``window=0``).

    ``points`` float64 [n, 3], each return in a frame rigid within its sweep (the vehicle frame
    of its frame, or its box frame); ``frame`` int [n] its sweep; ``sensor`` float64 [n, 3] the
    position of the lidar that measured it, in the same frame; ``rows`` int [k] the returns to
    move (None: all), an even subset of a dense object's returns: every return makes the surface,
    but the normals are fitted on ``rows`` alone (PCA over :data:`SWEEP_NORMAL_NEIGHBOURS` of them
    of the same sweep) and each other return takes its nearest one's. Nothing depends on the poses
    between sweeps: the registration (:mod:`drivetrack.refine`) can use it before it has poses.
    ``points`` must hold the returns on both sides of the surface (a box grown by a margin), as
    :func:`points_on_surface` says. The detection runs first on the :data:`SNAP_NOISE_FRAMES`
    frames it measures alone: with exact ranges no other frame's normals are fitted.
    """
    points = np.ascontiguousarray(points, dtype=np.float64)
    frame = np.asarray(frame, dtype=np.int64)
    sensor = np.asarray(sensor, dtype=np.float64)
    n = points.shape[0]
    rows = np.arange(n) if rows is None else np.asarray(rows, dtype=np.int64)
    chosen = np.zeros(n, dtype=bool)
    chosen[rows] = True
    # the detection first, on the few frames it measures (exact ranges: no normals for the others)
    probe = np.isin(frame, _noise_frames(frame[rows]))
    if not _sweep_moves(points[probe], frame[probe], sensor[probe], chosen[probe], max_move_m)[1].any():
        return points[rows].copy(), np.zeros(rows.size, dtype=bool)
    out, moved = _sweep_moves(points, frame, sensor, chosen, max_move_m)
    return out[rows], moved[rows]


def _noise_frames(frame: np.ndarray) -> np.ndarray:
    """int64 [<= SNAP_NOISE_FRAMES]: the frames, evenly spread over those of ``frame`` int [n], on
    which :func:`points_on_surface` measures the range noise."""
    present = np.unique(frame)
    return present[np.unique(np.linspace(0, present.size - 1, min(present.size, SNAP_NOISE_FRAMES)).astype(np.int64))]


def _sweep_moves(points: np.ndarray, frame: np.ndarray, sensor: np.ndarray, chosen: np.ndarray,
                 max_move_m: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`points_on_sweep_surface` of the ``chosen`` bool [n] points, for all n."""
    n = points.shape[0]
    normal, usable = np.zeros((n, 3)), np.zeros(n, dtype=bool)
    order = np.argsort(frame, kind="stable")
    _, starts = np.unique(frame[order], return_index=True)
    for at in np.split(order, starts[1:]) if n else []:
        fit = at[chosen[at]]
        # the registration's surface: no second pass (not measured there; docs/visibility.md
        # "Planes that pass through their points")
        fitted = cloud_normals(points[fit], SWEEP_NORMAL_NEIGHBOURS, precise_m=0.0) if fit.size else None
        if fitted is not None:      # each return takes its nearest fitted one's (surfel_normals)
            surfels = surfel_normals(points[at], sensor[at], fitted=fitted)
            normal[at], usable[at] = surfels.normal, surfels.reliable
    surface = SurfaceCloud(*_by_frame(points, normal, frame))
    return points_on_surface(points, frame, points - sensor, normal, surface, usable & chosen, max_move_m,
                             window=0, radius_m=SWEEP_RADIUS_M, min_returns=SWEEP_MIN_RETURNS,
                             min_noise_m=SWEEP_MIN_NOISE_M)


def _remembered_steps(surface: SurfaceCloud, keys: np.ndarray, steps_of) -> np.ndarray:
    """float64 [k]: the steps of the points with unique ``keys`` int64 [k]: those remembered in
    ``surface``, the others ``steps_of(positions int [m])`` (then remembered too)."""
    known_keys, known = surface.remembered
    at = np.minimum(np.searchsorted(known_keys, keys), max(known_keys.size - 1, 0))
    hit = known_keys[at] == keys if known_keys.size else np.zeros(keys.size, dtype=bool)
    step = np.empty(keys.size)
    step[hit] = known[at[hit]]
    missing = np.flatnonzero(~hit)
    if missing.size:
        step[missing] = steps_of(missing)
        all_keys = np.concatenate([known_keys, keys[missing]])
        order = np.argsort(all_keys, kind="stable")
        # one assignment: another thread's call sees the old pair or the new one, never a mix
        surface.remembered = (all_keys[order], np.concatenate([known, step[missing]])[order])
    return step


def _by_frame(points: np.ndarray, normal: np.ndarray, frame: np.ndarray) -> tuple:
    """``(points, normal, frames, offsets)`` of a :class:`SurfaceCloud`: the rows sorted by frame."""
    order = np.argsort(frame, kind="stable")
    frames, starts = np.unique(np.asarray(frame)[order], return_index=True)
    return (np.ascontiguousarray(points[order], dtype=np.float64), np.ascontiguousarray(normal[order], dtype=np.float64),
            frames.astype(np.int64), np.append(starts, order.size).astype(np.int64))


def _steps_to_surface(points_box: np.ndarray, frame: np.ndarray, incidence: np.ndarray, normal: np.ndarray,
                      surface: SurfaceCloud, rows: np.ndarray, window: int, radius_m: float = SNAP_RADIUS_M,
                      min_returns: int = SNAP_MIN_RETURNS) -> np.ndarray:
    """float64 [len(rows)]: how far (metres) each point ``rows`` int [k] of ``points_box`` lies from
    the surface along its ray (:func:`points_on_surface`), NaN where its frame's returns are too few."""
    from drivetrack.visibility import kernel

    offset = np.full(rows.size, np.nan)
    min_cos = float(np.cos(np.radians(SNAP_MAX_TILT_DEG)))
    row_frame = frame[rows]
    for i in np.flatnonzero(np.isin(surface.frames, row_frame)):
        at = np.flatnonzero(row_frame == surface.frames[i])
        near = np.flatnonzero(np.abs(surface.frames - surface.frames[i]) <= window)
        lo, hi = surface.offsets[near[0]], surface.offsets[near[-1] + 1]
        cloud = surface.points[lo:hi]
        grid = kernel.cloud_grid(cloud, kernel.grid_cell(cloud))
        offset[at] = kernel.surface_offsets(grid, surface.normal[lo:hi], points_box[rows[at]], normal[rows[at]],
                                            float(radius_m), SNAP_SLAB_M, min_cos, int(min_returns))
    with np.errstate(divide="ignore", invalid="ignore"):
        return offset / incidence[rows]


def box_face_normals(points_box: np.ndarray, size: np.ndarray, skin_m: float) -> tuple[np.ndarray, np.ndarray]:
    """The label box's face normal at each point that lies on exactly one of its faces.

    ``points_box`` float [n, 3] (box frame, metres), ``size`` float [3] (length, width, height).
    Returns (normal float64 [n, 3] unit outward, zero where undefined; on_face bool [n]): a point
    is on a face when it lies within ``skin_m`` of that face's plane (either side) and more than
    ``skin_m`` inside the box's extent along both other axes (not at an edge or a corner, where
    the face is ambiguous).
    """
    p = np.asarray(points_box, dtype=np.float64)
    half = 0.5 * np.asarray(size, dtype=np.float64)
    near = np.abs(np.abs(p) - half) <= skin_m                                              # [n, 3]
    inner = np.abs(p) < half - skin_m                                                      # [n, 3]
    on_face = np.zeros(p.shape[0], dtype=bool)
    normal = np.zeros_like(p)
    for axis in range(3):
        others = [a for a in range(3) if a != axis]
        sel = near[:, axis] & inner[:, others[0]] & inner[:, others[1]]
        normal[sel, axis] = np.sign(p[sel, axis])
        on_face |= sel
    return normal, on_face


def with_box_face_normals(surfels: SurfelNormals, points_box: np.ndarray, size: np.ndarray,
                          skin_m: float) -> SurfelNormals:
    """``surfels`` with each unreliable normal of a point on exactly one face of the label box
    (:func:`box_face_normals`, ``points_box`` float [n, 3], ``size`` float [3], metres) replaced
    by that face's outward normal, and that point counted reliable."""
    face_normal, on_face = box_face_normals(points_box, size, skin_m)
    fill = on_face & ~surfels.reliable
    normal = surfels.normal.copy()
    normal[fill] = face_normal[fill]
    return SurfelNormals(normal, surfels.reliable | fill)


def orient_outward(normal: np.ndarray, points_box: np.ndarray, sensor_box: np.ndarray) -> np.ndarray:
    """bool [n]: which of the unit normals ``normal`` float [n, 3] at ``points_box`` float [n, 3]
    (box frame, metres) point inwards and must be flipped.

    Two cues, the more decisive one per point: a lidar sees the outside of a surface, so the
    outward normal turns towards the sensor that saw the return (``sensor_box`` float [n, 3]);
    and the box centre (the origin) lies inside the object, so it turns away from it. The cue
    whose direction makes the larger angle with the surface's plane decides (the larger
    ``|cos|``): the sensor for a face it saw head-on, the centre for a face the lidar saw at a
    grazing angle, where a few centimetres of pose error put the sensor on the wrong side of the
    plane (the sides of a car driving ahead; with 5 cm labels a third of their normals pointed
    inwards, docs/visibility.md "Normals turned outward by the more decisive cue").
    """
    to_sensor = sensor_box - points_box
    cos_sensor = np.einsum("ni,ni->n", normal, to_sensor) / np.maximum(np.linalg.norm(to_sensor, axis=-1), 1e-9)
    cos_centre = np.einsum("ni,ni->n", normal, points_box) / np.maximum(np.linalg.norm(points_box, axis=-1), 1e-9)
    return np.where(np.abs(cos_centre) > np.abs(cos_sensor), cos_centre < 0, cos_sensor < 0)


def camera_centres_box(camera_from_box: np.ndarray, shift_camera: np.ndarray) -> np.ndarray:
    """float64 [T, 3]: the camera centre in the box frame of each frame.

    ``camera_from_box`` float64 [T, 4, 4] and ``shift_camera`` float64 [T, 3] (metres, added in
    the camera frame) map box points as ``R p + t + shift``; the centre solves ``R p + t + shift = 0``.
    """
    rotation, translation = camera_from_box[:, :3, :3], camera_from_box[:, :3, 3] + shift_camera
    return -np.einsum("tji,tj->ti", rotation, translation)


#: The own-box gap limit counts a ray as passing through the box itself only where it runs this
#: deep inside it (metres): a few centimetres of label or extent error put a grazing roof's smear
#: inside the box, a cabin in front of a bonnet lies decimetres deep.
OWN_BOX_DEPTH_M = 0.1


def own_box_parameters(centres_box: np.ndarray, size: np.ndarray, margin_m: float,
                       max_gap_m: float | None = None, solid: np.ndarray | None = None) -> np.ndarray:
    """float64 [T, 13]: per frame the camera centre in the box frame (``centres_box`` float [T, 3],
    :func:`camera_centres_box`), the half extents of the box of ``size`` float [T, 3] (metres)
    grown by ``margin_m`` on every side, ``max_gap_m`` (metres; None: +inf), the farthest in
    front of the point along its ray that a surface inside that box is always taken for the
    object's own (farther, only if the ray from it does not run through the box itself), then the
    half extents and the centre of the box itself, the ray must run through: the part of the box
    the object fills (``solid`` float [T, 2, 3], low and high corners, :func:`solid_extents`; None:
    the box) less :data:`OWN_BOX_DEPTH_M` on every side (at least 0): what :func:`own_surface`
    and the track kernel's depth test (``drivetrack.tracks.kernel``) take."""
    centres_box = np.asarray(centres_box, dtype=np.float64)
    size = np.broadcast_to(np.asarray(size, dtype=np.float64), centres_box.shape)
    half = 0.5 * size + float(margin_m)
    gap = np.full((centres_box.shape[0], 1), np.inf if max_gap_m is None else float(max_gap_m))
    if solid is None:
        solid = np.stack([-0.5 * size, 0.5 * size], axis=1)
    solid = np.asarray(solid, dtype=np.float64)
    itself = np.maximum(0.5 * (solid[:, 1] - solid[:, 0]) - OWN_BOX_DEPTH_M, 0.0)
    return np.ascontiguousarray(np.concatenate([centres_box, half, gap, itself, 0.5 * (solid[:, 1] + solid[:, 0])],
                                               axis=-1))


def own_surface(points_box: np.ndarray, depth_ratio: np.ndarray, own: np.ndarray,
                where: np.ndarray | None = None, reliable: np.ndarray | None = None) -> np.ndarray:
    """bool [T, n]: the depth-map surface in front of each point-frame is the object's own.

    ``points_box`` float [n, 3]; ``depth_ratio`` float [T, n] = the depth map's value at the
    point's pixel over the point's own z-depth (the surface's point on the ray from the camera
    centre ``e`` is ``e + depth_ratio (p - e)``: the pixel is the projection of the point, so they
    share the ray); ``own`` float64 [T, 13] from :func:`own_box_parameters`. True where that
    surface point lies inside the grown box and either at most ``own[:, 6]`` metres in front of
    the point along the ray, or farther but with the ray from it to ``own[:, 6]`` in front of the
    point not running through the box itself (the part its returns fill), :data:`OWN_BOX_DEPTH_M` deep (through the margin,
    where no part of the object is, only the map's spread: over a roof seen at a grazing angle the
    ray runs a few centimetres above the roof); where that stretch of the ray passes through the
    box, a part of the object itself hides the point (a cabin in front of a bonnet; a box has no
    such part). NaN ratios give False. ``where`` bool [T, n]: compute only there (False
    elsewhere; the callers ask about the few point-frames the test decides). ``reliable`` bool
    [n] (None: all): the points whose normal the back-face test can use; at the others no gap is
    taken for the object's own without the ray test (the limit is 0): the surface is its own
    smear only where the ray from it to the point itself runs outside the box itself, so a face
    the object turns away (the ray crosses its body) is still hidden by the map, and a roof seen
    at a grazing angle, too thinly sampled for a normal, is not.
    """
    points_box = np.asarray(points_box, dtype=np.float64)
    depth_ratio = np.asarray(depth_ratio, dtype=np.float64)
    if where is None:
        where = np.ones(depth_ratio.shape, dtype=bool)
    t_idx, n_idx = np.nonzero(where)
    out = np.zeros(depth_ratio.shape, dtype=bool)
    with np.errstate(invalid="ignore"):
        surface = _surface_points(points_box, depth_ratio, own, t_idx, n_idx)
        gap = np.linalg.norm(points_box[n_idx] - surface, axis=-1)
        limit = own[t_idx, 6] if reliable is None else np.where(np.asarray(reliable, bool)[n_idx], own[t_idx, 6], 0.0)
        far = gap > limit
        # farther than the gap: the object's own only if the ray from the surface to the gap's
        # start runs outside the box itself (through the margin: the map's spread)
        through = np.zeros(gap.shape, dtype=bool)
        if far.any():
            f = np.flatnonzero(far)
            p = points_box[n_idx[f]]
            stop = p + (surface[f] - p) * (limit[f] / gap[f])[:, None]
            middle = own[t_idx[f], 10:13]
            through[f] = _segment_enters_box(surface[f] - middle, stop - middle, own[t_idx[f], 7:10])
        out[t_idx, n_idx] = np.all(np.abs(surface) <= own[t_idx, 3:6], axis=-1) & ~through
    return out


def _surface_points(points_box: np.ndarray, depth_ratio: np.ndarray, own: np.ndarray, t_idx: np.ndarray,
                    n_idx: np.ndarray) -> np.ndarray:
    """float64 [m, 3]: the depth map's surface point on the ray from the camera centre ``e``
    (``own[t_idx, :3]``) through each point-frame (``t_idx``, ``n_idx`` int [m]): ``e + ratio (p - e)``."""
    centre = own[t_idx, :3]
    return centre + depth_ratio[t_idx, n_idx, None] * (points_box[n_idx] - centre)


#: A face of an object's box counts as solid up to its outermost return (:func:`solid_extents`) when
#: those returns come within this of the face (metres: a label drawn a few centimetres to decimetres
#: wide, a static object's box grown to hold its returns); farther (a face no sweep reached), up to
#: the face itself. The bottom face always stays (the ground clearance ends the returns there).
SOLID_FACE_MAX_M = 0.3


def solid_extents(points_box: np.ndarray, size: np.ndarray, max_gap_m: float = SOLID_FACE_MAX_M) -> np.ndarray:
    """float64 [r, 2, 3]: the low and high corners (box frame, metres) of the part of each box of
    ``size`` float [r, 3] its object fills, from the object's returns ``points_box`` float [m, 3]
    in that frame.

    Each face but the bottom moves in to the outermost return when that return lies within
    ``max_gap_m`` inside it, else stays (never moves out; the bottom always stays: the returns end
    at the ground clearance above it, not where the object does). A label is drawn a few
    centimetres to decimetres wide of its object (by hand, or a static object's box grown to hold
    the returns of its one pose), so a ray that crosses the label box near its face may pass beside
    the object itself: the depth-map tests leave such a ray to the z-buffer (:func:`other_surface`)
    and take a surface there for the object's own smear (:func:`own_surface`)."""
    half = 0.5 * np.asarray(size, dtype=np.float64).reshape(-1, 3)
    lo, hi = -half, half.copy()
    points_box = np.asarray(points_box, dtype=np.float64)
    if points_box.shape[0]:
        p_lo, p_hi = points_box.min(axis=0), points_box.max(axis=0)
        move_lo = (p_lo > lo) & (p_lo - lo <= max_gap_m)
        move_lo[..., 2] = False         # the bottom: the ground clearance, not the object, ends the returns there
        lo = np.where(move_lo, p_lo, lo)
        hi = np.where((p_hi < hi) & (hi - p_hi <= max_gap_m), p_hi, hi)
    return np.stack([lo, hi], axis=1)


def other_boxes(camera_from_box: np.ndarray, shift_camera: np.ndarray, others: list[tuple], margin_m: float) -> np.ndarray:
    """float64 [T, K, 21]: the other labelled objects' boxes in this object's box frame, per frame.

    ``camera_from_box`` float64 [T, 4, 4] and ``shift_camera`` float64 [T, 3] place this object
    (camera frame, metres: ``R p + t + shift``); ``others[tau]`` = (camera_from_box float64
    [m, 4, 4] with the other objects' shifts added to the translation, size float64 [m, 3][,
    solid float64 [m, 2, 3]]) of the other objects posed for that image, ``solid`` the part of
    each box its object fills (:func:`solid_extents`; default the box). Each slot holds the 9
    rotation and 3 translation values of ``box_other_from_box_self``, the other box's half extents
    grown by ``margin_m``, then the solid part's half extents and its centre (the other's box
    frame); unused slots have half extents -1 (:func:`other_surface`, the track kernel's depth test).
    """
    t_count = camera_from_box.shape[0]
    k_max = max((o[1].shape[0] for o in others), default=0)
    out = np.full((t_count, k_max, 21), -1.0)
    for tau, other in enumerate(others):
        camera_from_other, size = other[0], other[1]
        m = size.shape[0]
        if m == 0:
            continue
        solid = other[2] if len(other) > 2 else np.stack([-0.5 * size, 0.5 * size], axis=1)
        rotation, translation = camera_from_other[:, :3, :3], camera_from_other[:, :3, 3]
        r_self, t_self = camera_from_box[tau, :3, :3], camera_from_box[tau, :3, 3] + shift_camera[tau]
        # other <- camera <- self: R_o^T (R_s q + t_s - t_o)
        out[tau, :m, :9] = np.einsum("mji,jk->mik", rotation, r_self).reshape(m, 9)
        out[tau, :m, 9:12] = np.einsum("mji,mj->mi", rotation, t_self[None] - translation)
        out[tau, :m, 12:15] = 0.5 * size + float(margin_m)
        out[tau, :m, 15:18] = 0.5 * (solid[:, 1] - solid[:, 0])
        out[tau, :m, 18:21] = 0.5 * (solid[:, 1] + solid[:, 0])
    return out


def _segment_enters_box(start: np.ndarray, stop: np.ndarray, half: np.ndarray) -> np.ndarray:
    """bool [...]: the segment from ``start`` to ``stop`` (float [..., 3], box frame) passes through
    the box of half extents ``half`` (float [..., 3]) before its end (slab test, t in [0, 1))."""
    d = stop - start
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - start) / d, (half - start) / d
    flat = np.abs(d) < 1e-12
    lo = np.where(flat, np.where(np.abs(start) <= half, -np.inf, np.inf), np.minimum(t1, t2))
    hi = np.where(flat, np.where(np.abs(start) <= half, np.inf, -np.inf), np.maximum(t1, t2))
    enter, leave = np.maximum(lo.max(axis=-1), 0.0), hi.min(axis=-1)
    return (enter <= leave) & (enter < 1.0)


def other_surface(points_box: np.ndarray, depth_ratio: np.ndarray, own: np.ndarray, others: np.ndarray,
                  where: np.ndarray | None = None) -> np.ndarray:
    """bool [T, n]: the depth-map surface in front of each point-frame lies in another labelled
    object's box (grown) while the ray to the point misses that box itself: the map spread that
    object's returns beyond its outline, and its own surface in the z-buffer, not the map, decides.

    As :func:`own_surface` (``own`` float64 [T, 6] gives the camera centres), against the boxes
    ``others`` float64 [T, K, 21] of :func:`other_boxes` (the ray must cross the part of the box
    its object fills, :func:`solid_extents`). The depth maps are completed by nearest
    neighbour, which spreads a labelled occluder's returns a few pixels beyond its outline (points
    beside a pole, or just past a car's edge, were called hidden); the z-buffer draws that
    occluder from its own surface with its outline kept (:mod:`drivetrack.visibility.zbuffer`).
    A ray through the box is left to the map: there the z-buffer's holes (parts of the occluder no
    sweep sampled) would let hidden points through.
    """
    points_box = np.asarray(points_box, dtype=np.float64)
    depth_ratio = np.asarray(depth_ratio, dtype=np.float64)
    if where is None:
        where = np.ones(depth_ratio.shape, dtype=bool)
    out = np.zeros(depth_ratio.shape, dtype=bool)
    if others.shape[1] == 0:
        return out
    t_idx, n_idx = np.nonzero(where)
    centre = own[t_idx, :3]
    with np.errstate(invalid="ignore"):
        surface = _surface_points(points_box, depth_ratio, own, t_idx, n_idx)                # [m, 3]
        slots = others[t_idx]                                                                # [m, K, 21]
        rotation = slots[..., :9].reshape(-1, slots.shape[1], 3, 3)

        def to_other(points):                                                                # [m, 3] -> [m, K, 3]
            return np.einsum("mkij,mj->mki", rotation, points) + slots[..., 9:12]

        inside = np.all(np.abs(to_other(surface)) <= slots[..., 12:15], axis=-1) & (slots[..., 12] >= 0)
        solid_centre = slots[..., 18:21]
        through = _segment_enters_box(to_other(centre) - solid_centre, to_other(points_box[n_idx]) - solid_centre,
                                      slots[..., 15:18])
    out[t_idx, n_idx] = (inside & ~through).any(axis=-1)
    return out


def facing_mask(points_box: np.ndarray, surfels: SurfelNormals, centres_box: np.ndarray,
                max_angle_deg: float) -> np.ndarray:
    """bool [T, n]: the point's face turns towards the camera (or its normal is unreliable).

    A face turns towards the camera when the angle between its outward normal and the direction
    to the camera centre is below ``max_angle_deg`` (90: any face not turned away).
    """
    return facing_test(points_box, surfels, centres_box, max_angle_deg)[0]


def facing_test(points_box: np.ndarray, surfels: SurfelNormals, centres_box: np.ndarray,
                max_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """``(facing bool [T, n], margin_deg float32 [T, n])`` from one :func:`facing_cosine`: the
    decision of :func:`facing_mask` and how far (degrees) the angle to the camera lies below
    ``max_angle_deg`` (negative: turned away; +inf at an unreliable normal)."""
    return _facing_from_cosine(facing_cosine(points_box, surfels.normal, centres_box), surfels, max_angle_deg)


def facing_test_towards(to_camera_box: np.ndarray, surfels: SurfelNormals,
                        max_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`facing_test` from each point-frame's own direction to the camera, ``to_camera_box``
    float [T, n, 3] (box frame, any length > 0): under a rolling shutter the camera centre at the
    point's capture time in its row, as the object is then (``TrackSource``'s numpy projection
    with ``towards=True``). A car beside a moving ego is seen from up to decimetres apart between
    the image pose and a row's time: degrees at a few metres, where its faces turn."""
    cosine = (np.einsum("tni,ni->tn", to_camera_box, surfels.normal)
              / np.maximum(np.linalg.norm(to_camera_box, axis=-1), 1e-9))
    return _facing_from_cosine(cosine, surfels, max_angle_deg)


def _facing_from_cosine(cosine: np.ndarray, surfels: SurfelNormals,
                        max_angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """:func:`facing_test`'s decision and margin from the cosines float [T, n]."""
    unreliable = ~surfels.reliable[None]
    facing = (cosine > np.cos(np.radians(max_angle_deg))) | unreliable
    angle = np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0)))
    return facing, np.where(unreliable, np.inf, max_angle_deg - angle).astype(np.float32)


def facing_cosine(points_box: np.ndarray, normal: np.ndarray, centres_box: np.ndarray) -> np.ndarray:
    """float64 [T, n]: cosine of the angle between each point's normal (float [n, 3], unit) and the
    direction from the point (float [n, 3]) to the camera centre of each frame (float [T, 3])."""
    to_camera = centres_box[:, None, :] - points_box[None]                         # [T, n, 3]
    return np.einsum("tni,ni->tn", to_camera, normal) / np.maximum(np.linalg.norm(to_camera, axis=-1), 1e-9)
