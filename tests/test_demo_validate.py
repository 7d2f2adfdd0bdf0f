"""``lunarnav demo``: bad settings and an --out in the way are reported in one line before
anything is rendered."""

import pytest

from lunarnav_ml import demo
from lunarnav_ml.cli import main
from lunarnav_ml.errors import ConfigError


@pytest.fixture
def no_rendering(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("rendered before the settings were checked")

    monkeypatch.setattr(demo, "render_splits", fail)


@pytest.mark.parametrize("option, value, message", [
    ("--train-minutes", "nan", "train_minutes must be a finite number > 0, got nan"),
    ("--train-minutes", "inf", "train_minutes must be a finite number > 0, got inf"),
    ("--train-minutes", "0", "train_minutes"),
    ("--preset", "bogus", "unknown preset 'bogus'"),
    ("--image-size", "100", "multiple of 32"),
])
def test_bad_setting_is_one_line_before_rendering(tmp_path, capsys, no_rendering, option, value,
                                                  message):
    code = main(["demo", "--out", str(tmp_path / "o"), "--no-progress", option, value])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0]
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("field, value", [
    ("max_fa_per_image", float("nan")), ("max_fa_per_image", -0.1), ("n_overlays", -1),
])
def test_other_float_and_count_settings_are_checked(field, value):
    with pytest.raises(ConfigError, match=field):
        demo.DemoConfig(**{field: value}).validate()


def test_known_presets_pass():
    from lunarnav_ml.models.presets import PRESETS

    for preset in PRESETS:
        demo.DemoConfig(preset=preset).validate()


def test_out_that_is_a_file_is_one_line_before_rendering(tmp_path, capsys, no_rendering):
    (tmp_path / "afile").write_text("x")
    code = main(["demo", "--out", str(tmp_path / "afile"), "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert f"{tmp_path / 'afile'}: output folder is an existing file" in err[0]
    assert "PosixPath" not in err[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["afile"]


def test_box_refiner_is_on_by_default_and_can_be_turned_off(monkeypatch, tmp_path):
    seen = []
    monkeypatch.setattr(demo, "run_demo", lambda cfg, out, progress: seen.append(cfg))
    assert main(["demo", "--out", str(tmp_path / "a"), "--no-progress"]) == 0
    assert main(["demo", "--out", str(tmp_path / "b"), "--no-progress", "--no-box-refiner"]) == 0
    assert [cfg.box_refiner for cfg in seen] == [True, False]


def test_summary_names_the_network_boxes_figure_beside_the_refined_one(capsys):
    metrics = {"coco": {"per_class": {"crater": {"AP50": 0.7, "AP": 0.3}}}, "threshold": 0.4,
               "false_alarms_per_image": 0.1, "crater_pd_D5_within20m": 0.5,
               "run": {"wall_seconds": 60.0, "peak_rss_gib": 2.0}}
    demo._print_summary(metrics)
    assert "crater AP50 0.700  AP 0.300" in capsys.readouterr().out
    demo._print_summary({**metrics, "network_boxes_coco": {
        "per_class": {"crater": {"AP50": 0.55, "AP": 0.2}}}})
    assert "crater AP50 0.700 (network's boxes 0.550)  AP" in capsys.readouterr().out
