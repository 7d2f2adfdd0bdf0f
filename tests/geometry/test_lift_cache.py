import pickle
from dataclasses import replace

import pytest

from lunarnav_ml.geometry.lifter import LifterConfig
from tests.bench_scripts import load_script
from tests.geometry.test_report import _write_dataset

lc = load_script("lift_cache")


@pytest.fixture(scope="module")
def cached(tmp_path_factory, crater_scene):
    root = tmp_path_factory.mktemp("lift_cache")
    _write_dataset(root / "set_a", crater_scene)
    assert lc.main(["cache", str(root / "set_a"), "--out", str(root / "cache"),
                    "--refiner", "none", "--range", "0", "30"]) == 0
    return root / "cache"


def test_the_windows_reproduce_the_reports_lifts(cached, capsys):
    data = lc.load(cached / "set_a.pkl")
    assert len(data["craters"]) == 1 and data["craters"][0]["row"]["ok"]
    assert lc.main(["lift", str(cached)]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("set_a |") and out[1].endswith("| 1/1 | reproduced 1/1")
    assert out[2].startswith("pooled |")


def test_a_changed_setting_changes_the_lift(cached, capsys):
    data = lc.load(cached / "set_a.pkl")
    same = lc.relift(data, {})
    moved = lc.relift(data, {"rim_offset": 0.3, "box_rim_offset": 0.3})
    assert same[0]["center_m"] == data["craters"][0]["row"]["center_m"]
    assert moved[0]["center_m"] != same[0]["center_m"]
    # a lift the window cannot hold is caught by the check: blank the disparity window
    data["craters"][0]["disp"][:] = float("nan")
    assert lc.mismatches([data["craters"][0]["row"]], lc.relift(data, {})) == 1


def test_today_starts_from_the_current_defaults(cached, capsys):
    """A cache written under older defaults: ``--today`` lifts with today's LifterConfig and
    the cached run's edge offsets; without it the cache's own settings stand."""
    data = lc.load(cached / "set_a.pkl")
    old = replace(data["settings"]["lifter"], box_rim_offset=0.3, match_half_width=3,
                  min_flank_rise_px=None)
    data["settings"]["lifter"] = old
    today = lc.todays_lifter(old)
    assert today == replace(LifterConfig(), box_rim_offset=0.3)
    now = lc.relift(data, {}, today=True)[0]["center_m"]
    assert now == lc.relift({**data, "settings": {**data["settings"], "lifter": today}},
                            {})[0]["center_m"]
    assert now != lc.relift(data, {})[0]["center_m"]
    assert lc.main(["lift", str(cached), "--today"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[1].startswith("set_a |") and "reproduced" not in out[1]


def test_bad_caches_and_settings_are_one_line(cached, tmp_path, capsys):
    assert lc.main(["lift", str(tmp_path)]) == 2
    assert "no lift cache" in capsys.readouterr().err
    (tmp_path / "x.pkl").write_bytes(b"not a pickle")
    assert lc.main(["lift", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("lift_cache: error:") and "x.pkl" in err and "\n" not in err
    (tmp_path / "x.pkl").write_bytes(pickle.dumps({"version": 0}))
    assert lc.main(["lift", str(tmp_path)]) == 2
    assert "version 1" in capsys.readouterr().err
    assert lc.main(["lift", str(cached), "--lifter", "nope=1"]) == 2
    assert "--lifter: expected FIELD=VALUE" in capsys.readouterr().err
    assert lc.main(["cache", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    assert "none" in capsys.readouterr().err and not (tmp_path / "o" / "none.pkl").exists()
    assert lc.main(["cache", str(tmp_path), "--out", str(tmp_path / "o"), "--disparity",
                    "rendered", "--refiner", "r.onnx"]) == 2
    assert "not the rendered one" in capsys.readouterr().err
