"""Stereo camera calibration from checkerboard views (OpenCV), and camera-to-hand extrinsics.

:func:`calibrate_stereo` (intrinsics + left→right extrinsics), :func:`hand_extrinsics`
(the pair's pose on the hand from one view of the board in a known fixture pose),
:func:`calibrate_rendered` (the whole procedure on MuJoCo renders, with the error against
the exact camera model). ``hil calibrate-camera`` runs it (docs/camera.md).
"""

from hilstack.calibration.camera.stereo import (
    CalibrationError,
    calibrate_from_images,
    calibrate_rendered,
    calibrate_stereo,
    compare,
    detect_corners,
    hand_extrinsics,
)

__all__ = ["CalibrationError", "calibrate_from_images", "calibrate_rendered", "calibrate_stereo", "compare",
           "detect_corners", "hand_extrinsics"]
