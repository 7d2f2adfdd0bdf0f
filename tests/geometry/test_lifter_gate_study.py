import json

import pytest

from lunarnav_ml.errors import LunarNavError
from tests.bench_scripts import load_script

study = load_script("lifter_gate_study")


def test_lifter_settings_are_typed_by_the_config_fields():
    got = study._lifter_settings(["snap_px=12", "crest_match=false", "rim_offset=0.1"])
    assert got == {"snap_px": 12, "crest_match": False, "rim_offset": 0.1}
    assert isinstance(got["snap_px"], int)
    assert study._lifter_settings([]) == {}
    # an optional threshold: a number, or none to turn it off
    assert study._lifter_settings(["min_flank_rise_m=0.02"]) == {"min_flank_rise_m": 0.02}
    assert study._lifter_settings(["min_flank_rise_m=none"]) == {"min_flank_rise_m": None}


@pytest.mark.parametrize("item", ["snap=12", "snap_px", "snap_px=", "method"])
def test_unknown_or_empty_lifter_settings_are_refused(item):
    with pytest.raises(LunarNavError, match="--lifter: expected FIELD=VALUE"):
        study._lifter_settings([item])


def test_a_setting_of_the_wrong_type_is_refused():
    with pytest.raises(LunarNavError, match="snap_px expects type int, got 'x'"):
        study._lifter_settings(["snap_px=x"])


def test_settings_this_option_cannot_parse_are_refused():
    with pytest.raises(LunarNavError, match="match_rows is a tuple"):
        study._lifter_settings(["match_rows=1,4"])
    with pytest.raises(LunarNavError, match="crest_match expects type bool, got 'yes'"):
        study._lifter_settings(["crest_match=yes"])
    assert study._lifter_settings(["method=plane"]) == {"method": "plane"}


def test_a_bad_setting_is_one_line_on_the_command_line(capsys, tmp_path):
    assert study.main([str(tmp_path / "a.json"), "--lifter", "nope=1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lifter_gate_study: error: --lifter") and "\n" not in err


def _row(ann_id, ok, resid, disp=10.0):
    return {"ann_id": ann_id, "ok": ok, "rim_residual_px": resid, "rim_disparity_px": disp,
            "crest_fraction": 0.5}


def test_a_failed_lift_is_replaced_by_its_retry_only_where_the_retry_passes():
    rows = [_row(1, True, 0.5), _row(2, True, 1.4), _row(3, True, 1.4), _row(4, False, 0.1)]
    retry = [_row(1, True, 9.0), _row(2, True, 0.9), _row(3, True, 1.2), _row(4, True, 0.2)]
    got = study.apply_gate(rows, 0.8, 0.10, 0.0, retry=retry)  # gate: 1.0 px at 10 px
    assert [r["ok"] for r in got] == [True, True, False, True]
    assert got[0] is rows[0] and got[1] is retry[1] and got[3] is retry[3]
    assert [r["ok"] for r in study.apply_gate(rows, 0.8, 0.10, 0.0)] == [True, False, False, False]


def test_as_is_prints_one_pooled_row_of_the_lifters_own_outcomes(capsys, tmp_path):
    def row(d, err, ok=True):
        return {"ann_id": 1, "diameter_m": d, "near_rim_range_m": 16.0, "ok": ok,
                "reason": "ok" if ok else "lift:stereo_inconsistent", "center_err_m": err,
                "center_err_xy_m": [err, 0.0], "diameter_err_m": 0.1, "sigma_h_m": 1.0}
    for stem, rows in (("a", [row(5.0, 1.0), row(10.0, 2.0, ok=False)]), ("b", [row(5.0, 1.0)])):
        (tmp_path / stem).mkdir()
        (tmp_path / stem / "geometry_craters.json").write_text(json.dumps(rows))
    argv = [str(tmp_path / "a.json"), str(tmp_path / "b.json"), "--out", str(tmp_path),
            "--as-is", "--rows-only"]
    assert study.main(argv) == 0
    out = capsys.readouterr().out.splitlines()
    # D = 5: 3 x RMS of two 1 m errors; D = 10 not lifted; Pd(3D) 2 of 3
    assert out[1].startswith("3.00 / nan |") and out[1].endswith("| 0.667 | 2")
