"""The camera stage's models: :mod:`drivetrack.camera.model` (the Waymo pinhole + distortion
model) and :mod:`drivetrack.camera.rolling_shutter` (rolling-shutter-aware projection over frames).
"""
