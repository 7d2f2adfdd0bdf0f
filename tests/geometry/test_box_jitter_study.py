import json

import pytest

from lunarnav_ml.geometry.report import geometry_report
from tests.bench_scripts import load_script
from tests.geometry.test_report import _write_dataset

study = load_script("box_jitter_study")


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, crater_scene):
    root = tmp_path_factory.mktemp("jitter_ds")
    _write_dataset(root, crater_scene)
    return root / "annotations.json"


def test_the_study_runs_each_source_and_jitter(dataset, tmp_path, capsys):
    out = tmp_path / "study"
    assert study.main([str(dataset), "--jitters", "0", "0.05", "--sources", "box", "fit",
                       "--out", str(out)]) == 0
    table = json.loads((out / "box_jitter.json").read_text())["table"]
    assert set(table) == {"box", "fit"} and set(table["box"]) == {"0", "0.05"}
    assert (out / "box_jitter.png").stat().st_size > 0
    # jitter 0 is the plain report on the labelled boxes
    plain = geometry_report(dataset, tmp_path / "plain", ellipse_source="box", plots=False)
    assert table["box"]["0"] == study.mean_figures([plain])
    assert table["box"]["0.05"] != table["box"]["0"]  # the moved boxes lift elsewhere
    assert "box jitter 0.05: mean 3σ centre" in capsys.readouterr().out


def test_a_missing_set_is_one_line(tmp_path, capsys):
    assert study.main([str(tmp_path / "none.json"), "--jitters", "0", "--out",
                       str(tmp_path / "o")]) == 2
    assert "none.json" in capsys.readouterr().err
