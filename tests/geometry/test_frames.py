import numpy as np
import pytest

from lunarnav_ml.errors import InputError
from lunarnav_ml.geometry.frames import (
    StereoRig,
    camera_to_rover,
    camera_to_rover_rotation,
    rover_to_camera,
)


def test_level_camera_axes():
    r = camera_to_rover_rotation(0.0)
    np.testing.assert_allclose(r @ [0, 0, 1], [1, 0, 0], atol=1e-12)  # forward
    np.testing.assert_allclose(r @ [1, 0, 0], [0, -1, 0], atol=1e-12)  # right = -left
    np.testing.assert_allclose(r @ [0, 1, 0], [0, 0, -1], atol=1e-12)  # down


def test_pitch_down_and_roll():
    p = 20.0
    fwd = camera_to_rover_rotation(p) @ [0, 0, 1]
    np.testing.assert_allclose(fwd, [np.cos(np.radians(p)), 0, -np.sin(np.radians(p))], atol=1e-12)
    right = camera_to_rover_rotation(0.0, 10.0) @ [1, 0, 0]
    assert right[2] < 0  # positive roll: right side down
    r = camera_to_rover_rotation(13.0, -4.0)
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)


def test_round_trip_and_ground_point():
    h, p = 1.5, 20.0
    # the optical axis meets the ground at h / tan(p) ahead
    d = h / np.tan(np.radians(p))
    cam = rover_to_camera([[d, 0.0, 0.0]], h, p)
    np.testing.assert_allclose(cam[0, :2], 0.0, atol=1e-12)
    assert cam[0, 2] == pytest.approx(np.hypot(d, h))
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(20, 3))
    np.testing.assert_allclose(camera_to_rover(rover_to_camera(pts, h, p, 3.0), h, p, 3.0), pts)


def test_matches_synth_camera_convention():
    # synth.camera.rotation_from_angles: columns are the camera axes in the scene frame
    synth_cam = pytest.importorskip("lunarnav_ml.synth.camera")
    for pitch, roll in ((20.0, 0.0), (12.0, 5.0), (-3.0, -7.0)):
        np.testing.assert_allclose(
            camera_to_rover_rotation(pitch, roll),
            synth_cam.rotation_from_angles(0.0, pitch, roll), atol=1e-12,
        )


def test_rig_from_camera_record():
    rec = {"height_m": 1.5, "pitch_deg": 20.0, "roll_deg": 0.0, "fov_deg": 90.0,
           "baseline_m": 0.3, "fx": 512.0, "fy": 512.0, "cx": 511.5, "cy": 511.5}
    rig = StereoRig.from_camera_record(rec)
    assert rig.focal_px == 512.0 and rig.height_m == 1.5
    np.testing.assert_allclose(rig.rays([[511.5, 511.5]]), [[0, 0, 1]])
    with pytest.raises(InputError, match="missing"):
        StereoRig.from_camera_record({"fx": 1.0})
    with pytest.raises(InputError, match="fx"):
        StereoRig.from_camera_record({**rec, "fy": 500.0})
    with pytest.raises(InputError, match="camera: height_m must be a finite number, got 'tall'"):
        StereoRig.from_camera_record({**rec, "height_m": "tall"})
    with pytest.raises(InputError, match="camera: pitch_deg must be a finite number"):
        StereoRig.from_camera_record({**rec, "pitch_deg": float("nan")})
    assert StereoRig.from_camera_record({k: v for k, v in rec.items() if k != "roll_deg"}) == rig


@pytest.mark.parametrize(("field", "value", "match"), [
    ("fx", -512.0, "camera: fx must be positive, got -512.0"),  # not "fx and fy differ"
    ("fy", 0.0, "camera: fy must be positive"),
    ("baseline_m", -0.3, "camera: baseline_m must be positive"),
    ("height_m", -1.0, "camera: height_m must be positive, got -1.0"),
    ("height_m", 0.0, "camera: height_m must be positive"),
    ("pitch_deg", 400.0, r"camera: pitch_deg must lie in \[-90, 90\], got 400.0"),
    ("pitch_deg", -91.0, "camera: pitch_deg must lie in"),
    ("roll_deg", 200.0, r"camera: roll_deg must lie in \[-180, 180\]"),
])
def test_impossible_camera_records_name_the_field(field, value, match):
    rec = {"height_m": 1.5, "pitch_deg": 20.0, "baseline_m": 0.3, "fx": 512.0, "fy": 512.0,
           "cx": 511.5, "cy": 511.5}
    with pytest.raises(InputError, match=f"^{match}"):
        StereoRig.from_camera_record({**rec, field: value})


def test_principal_point_must_lie_in_the_image():
    rec = {"height_m": 1.5, "pitch_deg": 20.0, "baseline_m": 0.3, "fx": 64.0, "fy": 64.0,
           "cx": 63.5, "cy": 63.5}
    assert StereoRig.from_camera_record(rec, image_size=(128, 128)).cx == 63.5
    with pytest.raises(InputError, match=r"camera: cx \(5000.0\) lies outside the image, which "
                                         r"is 128 px wide \(expected 0..128\)"):
        StereoRig.from_camera_record({**rec, "cx": 5000.0}, image_size=(128, 128))
    with pytest.raises(InputError, match="camera: cy .* 32 px high"):
        StereoRig.from_camera_record(rec, image_size=(128, 32))


@pytest.mark.parametrize(("pitch", "roll"), [(15.0, -3.0), (25.0, 3.0), (-60.0, 0.0),
                                             (89.0, 45.0), (-10.0, -45.0), (-30.0, 0.0)])
def test_synth_camera_records_are_accepted(pitch, roll):
    # the extremes of synth.config's camera ranges (pitch -60..89, roll -45..45, height 0.1..20)
    synth_cam = pytest.importorskip("lunarnav_ml.synth.camera")
    for height in (0.1, 1.5, 20.0):
        for fov in (10.0, 90.0, 150.0):
            rig = synth_cam.make_rig(np.zeros(3), width=128, height=96, fov_deg=fov,
                                     height_m=height, yaw_deg=0.0, pitch_deg=pitch,
                                     roll_deg=roll, baseline_m=0.3)
            StereoRig.from_camera_record(rig.camera_dict(), image_size=(128, 96))
    with pytest.raises(InputError, match="positive"):
        StereoRig(0.0, 0.3, 1, 1, 1.5, 0)
