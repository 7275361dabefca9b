"""Visibility from each object's own surface (issue 15), beside the depth-map test of the track stage.

:mod:`drivetrack.visibility.facing`: surfel normals of an object from its own LiDAR returns in its
box frame, and the back-face test (a point whose surface turns away from the camera is hidden by
its own object, whatever the depth map says there).
"""
from drivetrack.visibility.facing import (SENSOR_VEHICLE_M, SurfelNormals, camera_centres_box, facing_mask,
                                          sensor_positions, surfel_normals)

__all__ = ["SENSOR_VEHICLE_M", "SurfelNormals", "camera_centres_box", "facing_mask", "sensor_positions",
           "surfel_normals"]
