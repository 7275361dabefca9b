"""Depth stage: sparse depth from LiDAR, a registry of completers, the max-of-4 look-up.

Depth maps are float32 ``[H, W]`` metres of z-depth (camera-frame x: distance along the optical
axis from the camera centre); ``0`` = unknown. See docs/depth.md.

    from drivetrack.depth import sparse_depth_from_points, get_completer, lookup_max4
    sparse = sparse_depth_from_points(points_vehicle, camera)   # float32 [H, W]
    dense = get_completer("nearest")(sparse)                   # float32 [H, W], 0 = unknown
    depth_at_tracks = lookup_max4(dense, pixels)               # float32 [...]

Built-in completers: ``nearest`` (CPU, OpenCV), ``ipbasic`` (CPU, OpenCV morphology),
``nearest-torch`` (batched, CUDA or CPU; needs torch). More come from plugins in the entry-point
group ``drivetrack.depth_completers`` or from :func:`register_completer`.
"""
from drivetrack.depth.completers import (DepthCompleter, IPBasicCompleter, NearestCompleter,
                                         default_max_reach_px)
from drivetrack.depth.lookup import lookup_max4
from drivetrack.depth.registry import (ENTRY_POINT_GROUP, CompleterPluginError,
                                       UnknownCompleterError, get_completer, list_completers,
                                       register_completer)
from drivetrack.depth.sparse import (apply_depth_bounds, bound_blind_zone, horizontal_depth_scale,
                                     see_through_returns, sparse_depth_from_pixels, sparse_depth_from_points)
from drivetrack.depth.torch_nearest import TorchNearestCompleter

__all__ = ["sparse_depth_from_points", "sparse_depth_from_pixels", "see_through_returns", "bound_blind_zone", "apply_depth_bounds",
           "horizontal_depth_scale", "get_completer", "list_completers", "lookup_max4", "register_completer", "DepthCompleter", "NearestCompleter", "IPBasicCompleter",
           "TorchNearestCompleter", "CompleterPluginError", "UnknownCompleterError",
           "ENTRY_POINT_GROUP", "default_max_reach_px"]

register_completer(NearestCompleter.name, NearestCompleter)
register_completer(IPBasicCompleter.name, IPBasicCompleter)
register_completer(TorchNearestCompleter.name, TorchNearestCompleter)
