"""benchmarks/bench_baselines.py: bad input is one line and exit status 2, not a traceback."""

from tests.bench_scripts import load_script

bench = load_script("bench_baselines")


def test_bad_model_width_and_missing_data_are_one_line(tmp_path, capsys):
    assert bench.main(["--lidar-data", str(tmp_path), "--lidar-model-width", "nan",
                       "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "model_width" in err[0]
    assert bench.main(["--lidar-data", str(tmp_path / "none"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "none" in err[0]
