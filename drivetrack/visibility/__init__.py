"""Visibility from each object's own surface (issue 15), beside the depth-map test of the track stage.

:mod:`drivetrack.visibility.facing`: surfel normals of an object from its own LiDAR returns in its
box frame, and the back-face test (a point whose surface turns away from the camera is hidden by
its own object, whatever the depth map says there).
:mod:`drivetrack.visibility.zbuffer`: the nearest-depth buffer of the other labelled objects'
returns in each image, and the test hiding a point behind another object's surface.
"""
from drivetrack.visibility.facing import (SENSOR_VEHICLE_M, SurfelNormals, camera_centres_box, facing_mask,
                                          sensor_positions, surfel_normals)
from drivetrack.visibility.zbuffer import hidden_by_others, nearest_depth

__all__ = ["SENSOR_VEHICLE_M", "SurfelNormals", "camera_centres_box", "facing_mask", "hidden_by_others",
           "nearest_depth", "sensor_positions", "surfel_normals"]
