"""Stereo crater stage: box -> rim ellipse -> 3D center on a ray-cast scene with known truth."""


import numpy as np
import pytest

from lunarnav_ml.errors import ConfigError, InputError
from lunarnav_ml.geometry.lifter import LifterConfig
from lunarnav_ml.runtime import OnnxDetector, StereoCraterLocalizer
from tests.geometry.geometry_scene import render_crater_scene


class TruthDetector:
    """Returns the true crater box (and a rock elsewhere) whatever the image."""

    class_names = ("crater", "rock", "artifact")

    def __init__(self, box_xywh):
        x, y, w, h = box_xywh
        self.boxes = np.array([[x, y, x + w, y + h], [0, 0, 10, 10]], np.float32)

    def predict(self, images, conf_thres=0.25, iou_thres=0.6):
        return [{"boxes": self.boxes, "scores": np.array([0.9, 0.8], np.float32),
                 "labels": np.array([1, 2])}]


@pytest.fixture(scope="module")
def scene():
    return render_crater_scene(6.0, 7.0, size=(480, 360), pitch_deg=10.0,
                               sun_zenith_deg=60.0, sun_azimuth_deg=30.0, seed=3)


def rgb(gray):
    return np.repeat(gray[:, :, None], 3, axis=2)


def test_crater_lifted_to_its_true_center(scene):
    loc = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig)
    craters = loc(rgb(scene.left), rgb(scene.right))
    assert len(craters) == 1  # the rock box is not a crater
    c = craters[0]
    assert c.ok, c.reason
    d = scene.crater.diameter
    assert np.hypot(*(c.center_m[:2] - scene.center_rover[:2])) < max(1.0, 0.25 * d)
    assert abs(c.diameter_m - d) < 0.25 * d
    assert c.ellipse is not None and 0 < c.ellipse_quality <= 1
    assert not c.refined  # no refiner


def test_the_refiner_gate_marks_the_craters_it_corrects(scene):
    from lunarnav_ml.geometry.refine import DisparityRefiner

    for gate, want in ((1000.0, True), (0.5, False)):
        loc = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig,
                                    refiner=DisparityRefiner(max_disparity_px=gate))
        craters = loc(rgb(scene.left), rgb(scene.right))
        assert [c.refined for c in craters] == [want]
        assert craters[0].ok, craters[0].reason


def test_the_lifter_reads_the_crest_from_the_pair(scene):
    """The localizer hands the lifter the image pair (LifterConfig.crest_match); without the
    pair, or with the match off, the lift is the matcher's alone."""
    on = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig)(rgb(scene.left),
                                                                    rgb(scene.right))[0]
    off = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig,
                                lifter=LifterConfig(crest_match=False))
    plain = off(rgb(scene.left), rgb(scene.right))[0]
    assert on.ok and plain.ok
    assert on.center_m[0] != plain.center_m[0]
    box = TruthDetector(scene.box).boxes[0]
    disp = off.disparity(rgb(scene.left), rgb(scene.right))
    no_pair = off.localize_box(rgb(scene.left), disp, box, 0.9)
    np.testing.assert_array_equal(no_pair.center_m, plain.center_m)


def test_lift_from_the_box_or_the_fitted_ellipse(scene):
    """By default the lift starts from the box's inscribed ellipse (with the box offsets);
    lift_from="fit" lifts the fitted one. The fitted ellipse is reported either way."""
    from lunarnav_ml.geometry.ellipse import Ellipse
    from lunarnav_ml.geometry.lifter import lift_crater

    left, right = rgb(scene.left), rgb(scene.right)
    by_box = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig)
    by_fit = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig, lift_from="fit")
    a, b = by_box(left, right)[0], by_fit(left, right)[0]
    assert a.ok and b.ok and a.center_m[0] != b.center_m[0]
    np.testing.assert_array_equal(a.ellipse.to_array(), b.ellipse.to_array())
    box = TruthDetector(scene.box).boxes[0]
    xywh = np.array([box[0], box[1], box[2] - box[0], box[3] - box[1]], np.float64)
    disp = by_box.disparity(left, right)
    want = lift_crater(Ellipse.from_box(xywh), disp, scene.rig, LifterConfig(), (left, right),
                       from_box=True)
    np.testing.assert_array_equal(by_box.localize_box(left, disp, box, 0.9, (left, right)).center_m,
                                  want.center_m)
    with pytest.raises(ConfigError, match="lift_from"):
        StereoCraterLocalizer(TruthDetector(scene.box), scene.rig, lift_from="label")
    # a fit that fails: lifting from the box does not need it, lifting from the fit does
    from lunarnav_ml.geometry.ellipse import EllipseFit

    def failing(image, box_xywh):
        return EllipseFit(None, 0.0, "no_crater_region", 0, np.zeros((0, 2)))

    c = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig, fitter=failing)(left, right)[0]
    assert c.ok and c.ellipse is None and c.ellipse_quality == 0.0
    np.testing.assert_array_equal(c.center_m, a.center_m)
    c = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig, fitter=failing,
                              lift_from="fit")(left, right)[0]
    assert not c.ok and c.reason == "ellipse:no_crater_region" and c.lift is None


def test_runs_with_the_onnx_detector(scene, onnx_path):
    loc = StereoCraterLocalizer(OnnxDetector(onnx_path), scene.rig, conf_thres=0.01)
    craters = loc(rgb(scene.left), rgb(scene.right))
    assert all(c.reason == "ok" or c.reason.split(":")[0] in ("ellipse", "lift")
               for c in craters)
    assert all(np.isfinite(c.center_m).all() == c.ok for c in craters)


def test_bad_pairs_and_detectors(scene):
    loc = StereoCraterLocalizer(TruthDetector(scene.box), scene.rig)
    left = rgb(scene.left)
    with pytest.raises(InputError, match="right"):
        loc(left, left[:-2])
    with pytest.raises(InputError, match=r"images\[1\].*uint8"):
        loc(left, left.astype(np.float32))

    class NoCraters(TruthDetector):
        class_names = ("rock", "artifact")

    with pytest.raises(ConfigError, match="no 'crater'"):
        StereoCraterLocalizer(NoCraters(scene.box), scene.rig)


def test_the_box_refiner_moves_the_detector_boxes(scene):
    from lunarnav_ml.geometry.boxrefine import BoxRefiner

    x, y, w, h = scene.box
    narrow = (x + 0.08 * w, y + 0.1 * h, 0.84 * w, 0.9 * h)  # a detector's too-narrow box
    plain = StereoCraterLocalizer(TruthDetector(narrow), scene.rig)(rgb(scene.left),
                                                                     rgb(scene.right))
    loc = StereoCraterLocalizer(TruthDetector(narrow), scene.rig, box_refiner=BoxRefiner())
    craters = loc(rgb(scene.left), rgb(scene.right))
    assert len(craters) == 1 and craters[0].ok, craters[0].reason
    assert not np.allclose(craters[0].box, plain[0].box)  # the refined box is the one kept
    assert loc.timing_ms["box_refine"] > 0 and plain[0].box[2] - plain[0].box[0] < 0.85 * w + 1
    assert plain[0].ok and "box_refine" in loc.timing_ms


class QualityRefiner:
    """A box refiner with a quality output that leaves the edges and rates every box alike."""

    has_quality = True
    path = "quality.onnx"

    def __init__(self, quality):
        self.quality = quality

    def refine_scored(self, gray, xywh):
        return np.asarray(xywh, np.float64), np.full(len(xywh), self.quality, np.float32)

    def __call__(self, gray, xywh):
        raise AssertionError("with a quality output the boxes are refined while scored")


class AskedDetector(TruthDetector):
    """A :class:`TruthDetector` that records the floor it was asked for."""

    def predict(self, images, conf_thres=0.25, iou_thres=0.6):
        self.asked = conf_thres
        return super().predict(images, conf_thres, iou_thres)


def test_a_quality_refiner_scores_the_crater_boxes_as_detect_does(scene):
    """``conf_thres`` holds for sqrt(score x quality), as in ``lunarnav detect``: the network
    runs at its square, and a box it scored above the threshold can fall under it."""
    det = AskedDetector(scene.box)
    loc = StereoCraterLocalizer(det, scene.rig, conf_thres=0.5, box_refiner=QualityRefiner(0.4))
    craters = loc(rgb(scene.left), rgb(scene.right))
    assert det.asked == pytest.approx(0.25)
    assert len(craters) == 1 and craters[0].score == pytest.approx(np.sqrt(0.9 * 0.4))
    assert craters[0].ok, craters[0].reason
    assert loc.timing_ms["detect"] > 0 and loc.timing_ms["box_refine"] > 0
    strict = StereoCraterLocalizer(AskedDetector(scene.box), scene.rig, conf_thres=0.7,
                                   box_refiner=QualityRefiner(0.4))
    assert strict(rgb(scene.left), rgb(scene.right)) == []  # 0.9 raw, 0.6 refined


def test_a_quality_refiner_needs_craters_as_label_one(scene):
    det = TruthDetector(scene.box)
    det.class_names = ("rock", "crater", "artifact")
    with pytest.raises(ConfigError, match="label 1"):
        StereoCraterLocalizer(det, scene.rig, box_refiner=QualityRefiner(0.5))


class ConstantRescorer:
    """A second-stage scorer that rates every crater box it is given at ``p``."""

    path = "rescorer.onnx"

    def __init__(self, p):
        self.p = p

    def __call__(self, features):
        return np.full(len(features), self.p, np.float32)


def test_a_box_rescorer_scores_the_crater_boxes_and_needs_a_quality_refiner(scene):
    """With a rescorer ``conf_thres`` holds for its probabilities; the network runs at the
    rescorer's floor, as in ``lunarnav detect``."""
    from lunarnav_ml.geometry.boxrescore import RAW_FLOOR

    det = AskedDetector(scene.box)
    loc = StereoCraterLocalizer(det, scene.rig, conf_thres=0.5, box_refiner=QualityRefiner(0.4),
                                box_rescorer=ConstantRescorer(0.8))
    craters = loc(rgb(scene.left), rgb(scene.right))
    assert det.asked == pytest.approx(min(0.25, RAW_FLOOR))
    assert len(craters) == 1 and craters[0].score == pytest.approx(0.8)  # not sqrt(0.9 x 0.4)
    low = StereoCraterLocalizer(AskedDetector(scene.box), scene.rig, conf_thres=0.5,
                                box_refiner=QualityRefiner(0.4), box_rescorer=ConstantRescorer(0.3))
    assert low(rgb(scene.left), rgb(scene.right)) == []
    for refiner in (None, QualityRefiner(0.4)):
        if refiner is not None:
            refiner.has_quality = False
        with pytest.raises(ConfigError, match="quality output"):
            StereoCraterLocalizer(TruthDetector(scene.box), scene.rig, box_refiner=refiner,
                                  box_rescorer=ConstantRescorer(0.8))
