"""benchmarks/bench_baselines.py: bad input is one line and exit status 2, not a traceback."""

import importlib.util
from pathlib import Path

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_baselines.py"
_spec = importlib.util.spec_from_file_location("bench_baselines", _PATH)
bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(bench)


def test_bad_model_width_and_missing_data_are_one_line(tmp_path, capsys):
    assert bench.main(["--lidar-data", str(tmp_path), "--lidar-model-width", "nan",
                       "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model_width" in err[0]
    assert bench.main(["--lidar-data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none" in err[0]
