"""benchmarks/plot_runs.py: curves of resumed runs are joined; bad logs are named."""

from pathlib import Path

import pytest

from lunarnav_ml.errors import InputError
from tests.bench_scripts import load_script

plot_runs = load_script("plot_runs")


HEADER = "epoch,step,train/loss,val/AP50,val/AP50_crater\n"


def _run(root: Path, versions: dict[int, str]) -> Path:
    for v, body in versions.items():
        d = root / "csv" / f"version_{v}"
        d.mkdir(parents=True)
        (d / "metrics.csv").write_text(HEADER + body)
    return root


def test_versions_joined_in_order_and_summarized(tmp_path):
    # version_10 sorts after version_2 by number, not by name; train rows carry no val value
    run = _run(tmp_path / "a", {
        2: "0,50,0.9,,\n0,99,,0.20,0.30\n1,199,,0.35,nan\n",
        10: "2,299,,0.31,0.40\n",
    })
    files = plot_runs.metrics_files(run)
    assert [f.parent.name for f in files] == ["version_2", "version_10"]
    curve = plot_runs.read_curve(files, "val/AP50_crater")
    assert curve == [(99, 0.30), (299, 0.40)]  # NaN skipped
    s = plot_runs.summarize(plot_runs.read_curve(files, "val/AP50"))
    assert s == {"n": 3, "last": 0.31, "last_step": 299, "best": 0.35, "best_step": 199}


def test_main_writes_the_plot_and_one_line_per_run_and_metric(tmp_path, capsys):
    a = _run(tmp_path / "a", {0: "0,99,,0.2,0.3\n"})
    b = _run(tmp_path / "b", {0: "0,99,,0.4,0.5\n0,199,,0.1,0.6\n"})
    out = tmp_path / "curves.png"
    assert plot_runs.main([str(a), str(b), "--labels", "x", "x", "--out", str(out)]) == 0
    assert out.stat().st_size > 1000
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("{")]
    assert len(lines) == 4 and '"best": 0.4' in lines[2] and '"last": 0.6' in lines[3]


@pytest.mark.parametrize("body, needle", [
    ("0,abc,,0.2,0.3\n", "line 2"),
    (None, "no metrics.csv"),
])
def test_bad_logs_are_named(tmp_path, body, needle):
    run = tmp_path / "r"
    if body is None:
        run.mkdir()
    else:
        _run(run, {0: body})
    with pytest.raises(InputError, match=needle):
        plot_runs.read_curve(plot_runs.metrics_files(run), "val/AP50")


@pytest.mark.parametrize("data, needle", [
    (b"\xff\xfe\x00garbage\x9c", "not a readable CSV"),
    (b"", "no 'step' column"),
])
def test_foreign_files_are_named(tmp_path, data, needle):
    path = tmp_path / "metrics.csv"
    path.write_bytes(data)
    with pytest.raises(InputError, match=needle):
        plot_runs.read_curve(plot_runs.metrics_files(path), "val/AP50")


def test_main_reports_one_line_and_writes_nothing(tmp_path, capsys):
    run = _run(tmp_path / "r", {0: "0,99,,0.2,0.3\n"})
    out = tmp_path / "c.png"
    assert plot_runs.main([str(run), "--metrics", "val/nope", "--out", str(out)]) == 2
    assert plot_runs.main([str(run), "--labels", "a", "b", "--out", str(out)]) == 2
    assert plot_runs.main([str(tmp_path / "missing"), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and "'val/nope'" in err[0] and "2 labels for 1 runs" in err[1]
    assert "missing" in err[2] and not out.exists()
