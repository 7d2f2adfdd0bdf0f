"""Renderer physics: disparity = f B / Z, shadows away from the sun, black sky."""

import numpy as np
import pytest

from lunarnav_ml.synth import pipeline as P

from .conftest import one_crater_spec


def test_disparity_equals_f_b_over_z(small_cfg):
    spec = one_crater_spec()
    out = P.render_item(spec, small_cfg, 128, stereo=True)
    fx = out.image_info["camera"]["fx"]
    hit = np.isfinite(out.depth)
    assert hit.mean() > 0.5
    np.testing.assert_allclose(out.disparity[hit], fx * 0.3 / out.depth[hit], rtol=1e-5)
    assert np.all(out.disparity[~hit] == 0)


def test_right_view_matches_disparity(small_cfg):
    """The scene point seen at left pixel (u, v) projects to (u - d, v) in the right camera."""
    spec = one_crater_spec(zenith=50.0, azimuth=60.0)
    out = P.render_item(spec, small_cfg, 128, stereo=True)
    rig = P.make_scene_rig(spec, P.TerrainCache().get(spec.terrain, small_cfg), small_cfg, 128)
    vs, us = np.nonzero(np.isfinite(out.depth))
    rays = rig.left.ray_dirs().reshape(128, 128, 3)[vs, us]
    z_axis = rig.left.rot[:, 2]
    pts = rig.left.position + rays * (out.depth[vs, us] / (rays @ z_axis))[:, None]
    uv, _ = rig.right.project(pts)
    np.testing.assert_allclose(uv[:, 0], us - out.disparity[vs, us], atol=1e-3)
    np.testing.assert_allclose(uv[:, 1], vs, atol=1e-3)


def _inner_wall_brightness(out, ann):
    """Mean brightness of the left and right halves of the crater's box."""
    x, y, w, h = (round(v) for v in ann["bbox"])
    patch = out.left[y: y + h, x: x + w].astype(float)
    return patch[:, : w // 2].mean(), patch[:, w // 2:].mean()


def test_shadows_fall_away_from_the_sun(small_cfg):
    """Sun to the right: the crater's inner wall on the sun side (right) lies in shadow."""
    right_sun = P.render_item(one_crater_spec(zenith=70.0, azimuth=90.0), small_cfg, 256,
                              stereo=False)
    left_sun = P.render_item(one_crater_spec(zenith=70.0, azimuth=270.0), small_cfg, 256,
                             stereo=False)
    ann = next(a for a in right_sun.annotations if a["category_id"] == 1)
    l_half, r_half = _inner_wall_brightness(right_sun, ann)
    assert r_half < 0.6 * l_half
    l_half, r_half = _inner_wall_brightness(left_sun, ann)
    assert l_half < 0.6 * r_half


def test_sky_is_black(small_cfg):
    out = P.render_item(one_crater_spec(pitch=0.0), small_cfg, 128, stereo=False)
    sky = ~np.isfinite(out.depth)
    assert sky[:20].all() and out.left[sky].max() <= 3


def test_supersampling_keeps_geometry_and_smooths(small_cfg):
    """2x render + Lanczos: same depth/ids as a 1x render, similar but not identical image."""
    from lunarnav_ml.synth.config import SynthConfig

    d = small_cfg.to_dict()
    d["camera"]["supersample"] = 2
    cfg2 = SynthConfig.from_dict(d)
    spec = one_crater_spec(zenith=60.0, azimuth=45.0)
    one = P.render_item(spec, small_cfg, 96, stereo=False)
    two = P.render_item(spec, cfg2, 96, stereo=False)
    np.testing.assert_array_equal(one.depth, two.depth)
    np.testing.assert_array_equal(one.ids, two.ids)
    diff = np.abs(one.left.astype(int) - two.left.astype(int))
    assert diff.mean() < 6 and diff.max() > 0


def test_shadow_map_is_the_same_along_either_axis():
    """The sweep for a sun mostly along y runs on the transpose: it must equal the x sweep of
    the transposed field, and a wall casts a shadow of the right length (h / tan(elev))."""
    from lunarnav_ml.synth.raycast import shadow_heights

    rng = np.random.default_rng(0)
    h = rng.normal(0, 0.05, (64, 64)).astype(np.float32)
    h[30, :] = 1.0  # a 1 m wall across x = 30
    along_x = shadow_heights(h, 1.0, 0.3, 0.5, 0.1)  # sun toward +x, 26.6 deg elevation
    along_y = shadow_heights(np.ascontiguousarray(h.T), 0.3, 1.0, 0.5, 0.1)
    np.testing.assert_allclose(along_y, along_x.T, rtol=0, atol=1e-6)
    # downstream of the wall (away from the sun, -x) the shadow height falls 0.05 m per cell
    drop = 0.1 * np.sqrt(1 + 0.3**2) * 0.5
    assert along_x[25, 10] == pytest.approx(1.0 - 5 * drop, abs=0.02)
    assert (along_x >= h).all()


def test_sub_dem_texture_shows_in_a_narrow_view_and_fades_in_a_wide_one(small_cfg):
    """The micro texture changes only the shading (same depth), adds local contrast where a
    pixel is much finer than its wavelength, and fades out where pixels are coarse."""
    import dataclasses

    def render(fov, slope, speckle):
        spec = dataclasses.replace(one_crater_spec(x=30.0, zenith=50.0, azimuth=60.0),
                                   fov_deg=fov, micro_slope_rms=slope, micro_albedo_rms=speckle)
        return P.render_item(spec, small_cfg, 128, stereo=False)

    def local_contrast(img):
        img = img.astype(float)
        return float(np.abs(np.diff(img, axis=1)).mean())

    plain, textured = render(15.0, 0.0, 0.0), render(15.0, 0.3, 0.2)
    np.testing.assert_array_equal(plain.depth, textured.depth)
    assert local_contrast(textured.left) > 2.0 * local_contrast(plain.left) + 1.0
    assert (textured.left != render(15.0, 0.3, 0.2).left).sum() == 0  # deterministic
    # 90 deg at 128 px: a pixel spans >= 5 cm beyond ~7 m, more than the 4 cm wavelength
    wide_plain, wide_textured = render(90.0, 0.0, 0.0), render(90.0, 0.3, 0.2)
    far = np.isfinite(wide_plain.depth) & (wide_plain.depth > 10.0)
    assert far.sum() > 1000
    np.testing.assert_array_equal(wide_plain.left[far], wide_textured.left[far])


def test_pebble_shadow_falls_away_from_the_sun_and_fades_with_the_footprint():
    """A pebble lights like a hemisphere (its sunward side faces the sun), shadows the soil
    behind it along the anti-sun direction (length r / sin(elevation)), not in front of it,
    and is gone where a pixel spans its diameter."""
    import math

    from lunarnav_ml.synth import render as R

    micro = R.MicroTexture(pebble_per_m2=100.0, pebble_max_radius_m=0.04, salt=3.0).params(1e-3)
    assert micro[5] == 1.0  # one pebble in every cell
    micro[5] = 0.2  # now one cell in five: take a pebble with no neighbour within 2 cells
    cell = micro[7]
    ci, cj = next((i, j) for i in range(40) for j in range(40)
                  if _alone(R, micro, i, j))
    x, y, r = R._pebble_at(ci, cj, micro)
    assert 0.01 - 1e-12 <= r <= 0.04
    assert ci * cell <= x - r and x + r <= (ci + 1) * cell  # inside its cell
    assert cj * cell <= y - r and y + r <= (cj + 1) * cell
    elev = math.radians(30.0)
    sun = np.array([math.cos(elev), 0.0, math.sin(elev)])  # sun toward +x
    fine = 1e-3  # a 1 mm pixel
    w, alb, sx, sy, shadow = R._pebbles(x + 0.5 * r, y, fine, micro, sun)
    assert (w, alb, shadow) == (1.0, R.PEBBLE_ALBEDO, 0.0)
    assert sx < 0.0 and abs(sy) < 1e-12  # the surface falls away from the pebble's top
    assert R._pebbles(x - 1.5 * r, y, fine, micro, sun)[4] == 1.0  # behind: shadowed
    assert R._pebbles(x - 1.9 * r, y, fine, micro, sun)[4] == 1.0  # r / sin(30 deg) = 2 r
    assert R._pebbles(x - 2.1 * r, y, fine, micro, sun)[4] == 0.0
    assert R._pebbles(x + 1.5 * r, y, fine, micro, sun)[4] == 0.0  # in front: lit
    assert R._pebbles(x, y + 1.2 * r, fine, micro, sun)[4] == 0.0  # beside it
    assert R._pebbles(x - 1.5 * r, y, 2.0 * 0.04, micro, sun)[0] == 0.0  # a pixel too coarse


def _alone(R, micro, i, j):
    """Cell (i, j) has a pebble and no other cell within two has one."""
    return R._pebble_at(i, j, micro)[2] > 0 and all(
        R._pebble_at(i + a, j + b, micro)[2] == 0
        for a in range(-2, 3) for b in range(-2, 3) if (a, b) != (0, 0))


def test_pebbles_dot_a_narrow_view_only_in_its_shading(small_cfg):
    """Pebbles change the shading only (same depth), add dark (shadow) and bright pixels
    close by in a narrow view, are deterministic, and leave a wide view's far field alone."""
    import dataclasses

    def render(fov, pebbles):
        spec = dataclasses.replace(one_crater_spec(x=30.0, zenith=60.0, azimuth=60.0),
                                   fov_deg=fov, pebble_per_m2=pebbles)
        return P.render_item(spec, small_cfg, 128, stereo=False)

    plain, dotted = render(15.0, 0.0), render(15.0, 40.0)
    np.testing.assert_array_equal(plain.depth, dotted.depth)
    diff = dotted.left.astype(int) - plain.left.astype(int)
    assert (diff < -10).mean() > 0.01 and (diff > 5).mean() > 0.005
    np.testing.assert_array_equal(dotted.left, render(15.0, 40.0).left)
    # the far field's radiance (the 8-bit images differ there too: the bright pebbles close
    # by move the 99.5th-percentile exposure)
    from lunarnav_ml.synth import render as R
    from lunarnav_ml.synth.camera import sun_vector
    from lunarnav_ml.synth.scene import hapke_params

    spec = dataclasses.replace(one_crater_spec(x=30.0, zenith=60.0, azimuth=60.0), fov_deg=90.0)
    scene = P.TerrainCache().get(spec.terrain, small_cfg)
    cam = P.make_scene_rig(spec, scene, small_cfg, 128).left
    prep = R.prepare(scene.ter, sun_vector(spec.sun_zenith_deg, spec.sun_azimuth_deg, 0.0))
    kw = {"w_soil": spec.w_soil, "hp": hapke_params(small_cfg, spec.w_soil), "max_range_m": 60.0}
    wide_plain = R.render_view(prep, cam, **kw)
    wide_dotted = R.render_view(prep, cam, micro=R.MicroTexture(pebble_per_m2=40.0), **kw)
    far = np.isfinite(wide_plain.depth) & (wide_plain.depth > 10.0)
    near = np.isfinite(wide_plain.depth) & (wide_plain.depth < 4.0)
    assert far.sum() > 1000 and near.sum() > 100
    np.testing.assert_array_equal(wide_plain.radiance[far], wide_dotted.radiance[far])
    assert (wide_plain.radiance[near] != wide_dotted.radiance[near]).mean() > 0.05
