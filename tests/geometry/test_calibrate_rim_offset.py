import json

import numpy as np
import pytest

from lunarnav_ml.errors import LunarNavError
from tests.bench_scripts import load_script

cal = load_script("calibrate_rim_offset")


def _rows(offset_m: float, offset_frac: float, view: float = 0.0, seed: int = 0,
          per_diameter: int = 60) -> list[dict]:
    """Lifts with no offset whose along-range error is what an edge ``offset_frac * r +
    offset_m + view * r * H / R`` in front of the crest causes (H = 1.5 m, R the near rim's
    range; plus a little noise and one failed lift)."""
    rng = np.random.default_rng(seed)
    rows = [{"ok": False, "diameter_m": 5.0}]
    for d in (5.0, 10.0, 15.0, 20.0):
        for _ in range(per_diameter):
            r, near, bearing = d / 2, rng.uniform(5, 20), rng.uniform(-0.6, 0.6)
            rho = near + r
            k0 = 1 - r / rho
            err = -(offset_m + offset_frac * r + view * r * 1.5 / near) / k0 + rng.normal(0, 0.02)
            u = np.array([np.cos(bearing), np.sin(bearing)])
            lateral = np.array([-u[1], u[0]]) * rng.normal(0, 0.1)
            rows.append({"ok": True, "diameter_m": d, "near_rim_range_m": near,
                         "truth_center_m": [*(rho * u), 0.1],
                         "center_err_xy_m": (err * u + lateral).tolist()})
    return rows


def test_recovers_a_known_offset():
    radius, near, need, height = cal.needed_offsets(_rows(-0.25, 0.12, -0.2))
    assert len(need) == 240 and np.all(near > 0) and np.all(height == 1.5)
    icpt, slope, view, cells = cal.fit_offset(radius, near, need, height)
    assert icpt == pytest.approx(-0.25, abs=0.03)
    assert slope == pytest.approx(0.12, abs=0.005)
    assert view == pytest.approx(-0.2, abs=0.02)
    assert {r for r, _ in cells} == {2.5, 5.0, 7.5, 10.0}
    assert all(n >= 5 for n, _, _ in cells.values()) and len(cells) >= 24


def test_the_view_term_is_zero_when_the_offset_does_not_depend_on_range():
    radius, near, need, height = cal.needed_offsets(_rows(-0.1, 0.07))
    icpt, slope, view, _ = cal.fit_offset(radius, near, need, height)
    assert (icpt, slope) == (pytest.approx(-0.1, abs=0.03), pytest.approx(0.07, abs=0.005))
    assert view == pytest.approx(0.0, abs=0.02)


def test_one_diameter_is_not_enough():
    rows = [r for r in _rows(0.0, 0.06) if r["diameter_m"] == 5.0]
    with pytest.raises(LunarNavError, match="two diameters"):
        cal.fit_offset(*cal.needed_offsets(rows))


def test_one_range_band_is_not_enough():
    rows = [r for r in _rows(0.0, 0.06) if not r["ok"] or 9 <= r["near_rim_range_m"] < 11]
    with pytest.raises(LunarNavError, match="two near-rim range bands"):
        cal.fit_offset(*cal.needed_offsets(rows))


def test_fitted_and_box_ellipses_get_their_own_offsets(tmp_path, capsys):
    rows = _rows(-0.2, 0.07, -0.15) + [{**r, "from_box": True} for r in _rows(0.0, 0.09, seed=1)]
    (tmp_path / "set0").mkdir()
    (tmp_path / "set0" / "geometry_craters.json").write_text(json.dumps(rows))
    assert cal.main(["unused.json", "--out", str(tmp_path), "--rows-only"]) == 0
    got = json.loads((tmp_path / "rim_offset.json").read_text())
    assert got["fitted_ellipses"]["rim_offset_m"] == pytest.approx(-0.2, abs=0.03)
    assert got["fitted_ellipses"]["rim_offset"] == pytest.approx(0.07, abs=0.005)
    assert got["fitted_ellipses"]["rim_offset_view"] == pytest.approx(-0.15, abs=0.02)
    assert got["box_ellipses"]["box_rim_offset_view"] == pytest.approx(0.0, abs=0.02)
    assert got["box_ellipses"]["box_rim_offset_m"] == pytest.approx(0.0, abs=0.03)
    assert got["box_ellipses"]["box_rim_offset"] == pytest.approx(0.09, abs=0.005)
    assert f"box_rim_offset={got['box_ellipses']['box_rim_offset']:.4f}" in capsys.readouterr().out
    assert (tmp_path / "box_rim_offset.png").is_file() and (tmp_path / "rim_offset.png").is_file()
    # what lunarnav eval --edge-offsets reads back
    from lunarnav_ml.geometry.lifter import load_edge_offsets

    cfg = load_edge_offsets(tmp_path / "rim_offset.json")
    assert cfg.rim_offset == got["fitted_ellipses"]["rim_offset"]
    assert cfg.box_rim_offset_m == got["box_ellipses"]["box_rim_offset_m"]


def test_the_terms_are_written_into_a_refiner(tmp_path, capsys):
    from lunarnav_ml.geometry.refine import DisparityRefiner
    from lunarnav_ml.training.refiner import RefinerNet, export_refiner

    refiner = export_refiner(RefinerNet(4, (1,)), tmp_path / "r.onnx")
    rows = _rows(-0.2, 0.07, -0.15) + [{**r, "from_box": True} for r in _rows(0.0, 0.09, seed=1)]
    (tmp_path / "set0").mkdir()
    (tmp_path / "set0" / "geometry_craters.json").write_text(json.dumps(rows))
    assert cal.main(["unused.json", "--out", str(tmp_path), "--rows-only",
                     "--refiner", str(refiner)]) == 0
    got = json.loads((tmp_path / "rim_offset.json").read_text())
    offsets = DisparityRefiner(refiner).edge_offsets
    assert set(offsets) == {"rim_offset", "rim_offset_m", "rim_offset_view", "box_rim_offset",
                            "box_rim_offset_m", "box_rim_offset_view"}
    for section in ("fitted_ellipses", "box_ellipses"):
        for key, value in got[section].items():
            if key in offsets:
                assert offsets[key] == pytest.approx(value, abs=1e-5)
    assert got["refiner"] == str(refiner) and "written into" in capsys.readouterr().out
    assert (DisparityRefiner(refiner).max_disparity_px, DisparityRefiner(refiner).passes) == (
        None, 1)
    assert cal.main(["unused.json", "--out", str(tmp_path), "--rows-only", "--refiner",
                     str(refiner), "--max-disparity", "12", "--passes", "2"]) == 0
    again = DisparityRefiner(refiner)  # the gate and passes the terms were fitted under
    assert (again.max_disparity_px, again.passes, again.edge_offsets) == (12.0, 2, offsets)
    with pytest.raises(SystemExit):  # a gate without a refiner to write it into
        cal.main(["unused.json", "--out", str(tmp_path), "--rows-only", "--max-disparity", "12"])
    assert "give --refiner" in capsys.readouterr().err


@pytest.mark.parametrize("bad, field", [({"near_rim_range_m": None}, "near_rim_range_m"),
                                        ({"center_err_xy_m": [0.1]}, "center_err_xy_m"),
                                        ({"truth_center_m": ["x", 1.0]}, "truth_center_m")])
def test_malformed_rows_give_one_line_naming_the_field(tmp_path, capsys, bad, field):
    rows = _rows(0.0, 0.06)
    rows[3] = {**rows[3], **bad}
    (tmp_path / "set0").mkdir()
    (tmp_path / "set0" / "geometry_craters.json").write_text(json.dumps(rows))
    assert cal.main(["unused.json", "--out", str(tmp_path), "--rows-only"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and f"row 3: {field}" in err
    (tmp_path / "set0" / "geometry_craters.json").write_text("{not json")
    assert cal.main(["unused.json", "--out", str(tmp_path), "--rows-only"]) == 2
    assert "not valid JSON" in capsys.readouterr().err
