"""Crater labels match the projected rim geometry; object boxes come from visible pixels."""

import math

import cv2
import numpy as np

from lunarnav_ml.synth import pipeline as P
from lunarnav_ml.synth.camera import make_rig
from lunarnav_ml.synth.config import SynthConfig

from .conftest import one_crater_spec, two_crater_spec


def _expected_rim(spec, cfg, size):
    """Rim circle projected independently: flat ground at z = 0, rim crest at the rim height."""
    scene = P.TerrainCache().get(spec.terrain, cfg)
    crater = scene.craters[-1]
    t = spec.terrain.targets[0]
    a = np.linspace(0, 2 * np.pi, 3600, endpoint=False)
    pts = np.stack([t.x + t.diameter / 2 * np.cos(a), t.y + t.diameter / 2 * np.sin(a),
                    np.full(a.size, crater.rim_height_m)], 1)
    rig = make_rig(np.zeros(3), width=size, height=size, fov_deg=90.0, height_m=1.5,
                   yaw_deg=0.0, pitch_deg=spec.pitch_deg, roll_deg=spec.roll_deg,
                   baseline_m=0.3)
    f = (size / 2) / math.tan(math.radians(45))
    pc = (pts - rig.left.position) @ rig.left.rot
    uv = np.stack([f * pc[:, 0] / pc[:, 2] + (size - 1) / 2,
                   f * pc[:, 1] / pc[:, 2] + (size - 1) / 2], 1)
    return uv


def test_single_crater_box_and_ellipse_match_projection(small_cfg):
    spec = one_crater_spec(diameter=8.0, x=12.0, y=1.5, roll=4.0)
    out = P.render_item(spec, small_cfg, 256, stereo=False)
    craters = [a for a in out.annotations if a["category_id"] == 1]
    assert len(craters) == 1
    ann = craters[0]
    uv = _expected_rim(spec, small_cfg, 256)
    x0, y0 = uv.min(0) + 0.5
    x1, y1 = uv.max(0) + 0.5
    bx, by, bw, bh = ann["bbox"]
    assert np.allclose([bx, by, bx + bw, by + bh], [x0, y0, x1, y1], atol=1.0)
    (cx, cy), (w, h), ang = cv2.fitEllipse(uv.astype(np.float32))
    ex = ann["ellipse"]
    assert np.allclose(ex[:4], [cx, cy, w / 2, h / 2], atol=1.0)
    assert abs((ex[4] - ang + 90) % 180 - 90) < 2.0
    assert not ann["ignore"]
    assert ann["near_rim_range_m"] == round(math.hypot(12.0, 1.5) - 4.0, 4)
    assert ann["diameter_m"] == 8.0


def test_crater_far_away_is_ignored():
    cfg = SynthConfig.from_dict({"terrain": {"extent_m": 120.0, "resolution_m": 0.25}})
    spec = one_crater_spec(diameter=10.0, x=45.0, y=0.0, pitch=8.0, height=8.0)
    out = P.render_item(spec, cfg, 256, stereo=False)
    anns = [a for a in out.annotations if a["category_id"] == 1 and a["diameter_m"] == 10.0]
    assert anns and all(a["ignore"] and "far" in a["ignore_reasons"] for a in anns)


def test_rock_boxes_come_from_visible_pixels(small_cfg):
    spec = one_crater_spec(rocks=0.3)
    out = P.render_item(spec, small_cfg, 256, stereo=False)
    rocks = [a for a in out.annotations if a["category_id"] == 2]
    assert rocks
    for a in rocks:
        x, y, w, h = a["bbox"]
        mask = out.ids == a["object_id"] + (1 << 20) * a["tile"]
        ys, xs = np.nonzero(mask)
        assert (xs.min(), ys.min(), xs.max() + 1, ys.max() + 1) == (x, y, x + w, y + h)
        assert a["ignore"] == (h < 6)


def test_a_rim_grazing_the_image_edge_writes_no_zero_width_box():
    from types import SimpleNamespace

    from lunarnav_ml.synth.config import LabelConfig
    from lunarnav_ml.synth.labels import _crater_ann

    cam = SimpleNamespace(width=64, height=64, position=np.zeros(3), to_cam=lambda p: p)
    crater = SimpleNamespace(radius=2.0, diameter=4.0, depth_m=0.5, degradation=0.1)
    a = np.linspace(0, 2 * np.pi, 360)
    zc, z, depth = np.ones(a.size), np.zeros(a.size), np.full((64, 64), 100.0)
    for right_edge, written in ((0.0002, False), (0.4, True)):  # box right edge, px
        uv = np.stack([-20.5 + right_edge + 20 * (np.cos(a) - 1) + 20, 30 + 3 * np.sin(a)], 1)
        ann = _crater_ann(crater, np.zeros(2), z, uv, zc, cam, depth, LabelConfig(), 1.0)
        assert (ann is not None) == written
        if ann is not None:
            assert ann["bbox"][2] > 0 and ann["ignore"] and "clipped" in ann["ignore_reasons"]


def test_surviving_bowl_is_the_relief_later_stamps_leave():
    from types import SimpleNamespace

    from lunarnav_ml.synth.craters import surviving_bowl

    def crater(x, y, d):
        return SimpleNamespace(x=x, y=y, radius=d / 2)

    def share(craters, i):
        return float(surviving_bowl(craters, 100.0, np.array([i]))[0])

    # a later twin keeps (r / R)^4 of the bowl: its mean over the disk is 1/3
    assert abs(share([crater(0, 0, 2), crater(0, 0, 2)], 0) - 1 / 3) < 0.01
    # inside a larger, later crater: little left; the later crater itself keeps all of its bowl
    inside = [crater(0, 0, 2), crater(1, 0, 6)]
    assert share(inside, 0) < 0.1 and share(inside, 1) == 1.0
    # a small later crater at the centre of a large one takes a small bite, not the crater
    bite = share([crater(0, 0, 10), crater(0, 0, 2)], 0)
    assert abs(bite - (1 - 0.04 * 2 / 3)) < 0.01
    # distances wrap around the DEM's period: the same overlap as 1.9 m apart without the wrap
    wrapped = share([crater(49.5, 0, 2), crater(-48.6, 0, 4)], 0)
    plain = share([crater(0.5, 0, 2), crater(2.4, 0, 4)], 0)
    assert 0.0 < wrapped < 1.0 and abs(wrapped - plain) < 1e-9
    # repeated indices (a crater's periodic copies) each get their crater's share
    assert np.allclose(surviving_bowl(inside, 100.0, np.array([1, 0, 1])),
                       [1.0, share(inside, 0), 1.0])


def test_a_crater_excavated_by_a_later_one_is_ignored_as_overprinted(small_cfg):
    for first_small, expect in ((True, True), (False, False)):
        spec = two_crater_spec(first_small)
        out = P.render_item(spec, small_cfg, 256, stereo=False)
        small = [a for a in out.annotations if a["category_id"] == 1 and a["diameter_m"] == 4.0]
        big = [a for a in out.annotations if a["category_id"] == 1 and a["diameter_m"] == 10.0]
        assert len(small) == 1 and len(big) == 1
        assert ("overprinted" in small[0]["ignore_reasons"]) == expect
        assert small[0]["ignore"] == expect and small[0]["iscrowd"] == int(expect)
        assert not big[0]["ignore"]
        if expect:
            assert small[0]["surviving_bowl_fraction"] < 0.5
        else:  # stamped last, the small crater is whole and takes a bite out of the big one
            assert small[0]["surviving_bowl_fraction"] == 1.0
            assert 0.5 < big[0]["surviving_bowl_fraction"] < 1.0


def test_a_tilted_sliver_is_ignored_as_edge_on(small_cfg):
    """DESIGN.md's 6 px height measured across the rim ellipse: a crater seen as a thin sliver
    counts no more when a camera roll tilts its box taller than 6 px."""
    off = SynthConfig.from_dict({**small_cfg.to_dict(), "labels": {"min_rim_minor_axis_px": 0}})
    cases = (  # (x of the 4 m crater, roll, config, expected reasons)
        (12.0, 0.0, small_cfg, ["small"]),  # level: its box is the ellipse's 5.2 px height
        (12.0, 30.0, small_cfg, ["edge_on"]),  # rolled: the same ellipse in a 22 px tall box
        (12.0, 30.0, off, []),  # the rule off: DESIGN.md's box height alone
        (10.0, 30.0, small_cfg, []),  # nearer, 7.5 px across: countable at any roll
    )
    for x, roll, cfg, reasons in cases:
        out = P.render_item(one_crater_spec(diameter=4.0, x=x, y=0.0, roll=roll), cfg, 256,
                            stereo=False)
        ann = [a for a in out.annotations if a["category_id"] == 1 and a["diameter_m"] == 4.0]
        assert len(ann) == 1
        assert ann[0]["ignore_reasons"] == reasons, (x, roll)
        assert ann[0]["ignore"] == bool(reasons)
        if roll:
            assert ann[0]["bbox"][3] > 20.0
