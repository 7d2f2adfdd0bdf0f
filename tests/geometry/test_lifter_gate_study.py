import importlib.util
from pathlib import Path

import pytest

from lunarnav_ml.errors import LunarNavError

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "lifter_gate_study.py"
_spec = importlib.util.spec_from_file_location("lifter_gate_study", _PATH)
study = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(study)


def test_lifter_settings_are_typed_by_the_config_fields():
    got = study._lifter_settings(["snap_px=12", "crest_match=false", "rim_offset=0.1"])
    assert got == {"snap_px": 12, "crest_match": False, "rim_offset": 0.1}
    assert isinstance(got["snap_px"], int)
    assert study._lifter_settings([]) == {}


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
