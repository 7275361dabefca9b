"""Visibility from each object's own surface (issue 15), beside the depth-map test of the track stage.

:mod:`drivetrack.visibility.facing`: surfel normals of an object from its own LiDAR returns in its
box frame, and the back-face test (a point whose surface turns away from the camera is hidden by
its own object, whatever the depth map says there); :func:`~drivetrack.visibility.facing.own_surface`:
whether the depth map's surface in front of a point is the object's own (then the back-face test,
not the depth map, decides); :func:`~drivetrack.visibility.facing.other_surface`: whether it lies in
another labelled object's box (then the z-buffer, not the depth map, decides);
:func:`~drivetrack.visibility.facing.points_on_surface`: each tracked return moved along its lidar
ray onto the surface of its object's returns round it, where the ranges are noisy.
:mod:`drivetrack.visibility.zbuffer`: the nearest-depth buffer of the other labelled objects'
returns in each image, and the test hiding a point behind another object's surface.
"""
from drivetrack.visibility.facing import (OWN_BOX_DEPTH_M, SENSOR_VEHICLE_M, CloudNormals, SurfaceCloud,
                                          SurfelNormals, box_face_normals, camera_centres_box, cloud_normals,
                                          facing_mask, facing_test, orient_outward, other_boxes, other_surface,
                                          own_box_parameters, own_surface, points_on_surface, points_on_sweep_surface,
                                          sensor_positions, solid_extents, surface_cloud, surfel_normals,
                                          with_box_face_normals)
from drivetrack.visibility.zbuffer import hidden_by_others, nearest_depth

__all__ = ["OWN_BOX_DEPTH_M", "SENSOR_VEHICLE_M", "CloudNormals", "SurfaceCloud", "SurfelNormals",
           "box_face_normals", "camera_centres_box", "cloud_normals", "facing_mask", "facing_test",
           "hidden_by_others", "nearest_depth", "orient_outward", "other_boxes", "other_surface",
           "own_box_parameters", "own_surface", "points_on_surface", "points_on_sweep_surface", "sensor_positions",
           "solid_extents", "surface_cloud", "surfel_normals", "with_box_face_normals"]
