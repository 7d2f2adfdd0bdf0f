"""lunarnav_ml.geometry: crater ellipses, pinhole/CAHV cameras, SGBM stereo, the range lifter
and the geometry evaluation (``geometry_report``)."""

from lunarnav_ml.geometry.cameras import (
    CAHVModel,
    PinholeCamera,
    StereoRectification,
    cahv_backproject,
    cahv_project,
    cahv_to_pinhole,
    change_pcam_pair,
    parse_cahv,
    pinhole_backproject,
    pinhole_from_fov,
    pinhole_project,
    pinhole_to_cahv,
    rectify_cahv_pair,
    rectify_images,
)
from lunarnav_ml.geometry.ellipse import (
    Ellipse,
    EllipseFit,
    EllipseFitter,
    fit_crater_ellipse,
    fit_ellipse_points,
)
from lunarnav_ml.geometry.frames import (
    StereoRig,
    camera_to_rover,
    camera_to_rover_rotation,
    rover_to_camera,
)
from lunarnav_ml.geometry.lifter import LifterConfig, LiftResult, lift_crater, rows_needed
from lunarnav_ml.geometry.stereo import (
    DisparityResult,
    SGBMStereo,
    compute_disparity,
    disparity_to_depth,
    disparity_to_points,
    match_strips,
)

__all__ = [
    "CAHVModel", "DisparityResult", "Ellipse", "EllipseFit", "EllipseFitter", "LiftResult",
    "LifterConfig", "PinholeCamera", "SGBMStereo", "StereoRectification", "StereoRig",
    "cahv_backproject", "cahv_project", "cahv_to_pinhole", "camera_to_rover",
    "camera_to_rover_rotation", "change_pcam_pair", "compute_disparity", "disparity_to_depth",
    "disparity_to_points", "fit_crater_ellipse", "fit_ellipse_points", "lift_crater",
    "match_strips", "parse_cahv",
    "pinhole_backproject", "pinhole_from_fov", "pinhole_project", "pinhole_to_cahv",
    "rectify_cahv_pair", "rectify_images", "rover_to_camera", "rows_needed",
]
