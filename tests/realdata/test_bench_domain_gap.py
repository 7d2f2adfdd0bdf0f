"""benchmarks/bench_domain_gap.py: the input-side sweep and its plot."""

import json
from pathlib import Path

from tests.bench_scripts import load_script
from tests.detector_fixtures import make_coco

gap = load_script("bench_domain_gap")

ROOT = Path(__file__).resolve().parents[2]
NANO = ROOT / "lunarnav_ml" / "weights" / "nano.pt"


def test_input_size_sweep_rows_plot_and_bad_size(tmp_path, capsys):
    ann = make_coco(tmp_path / "set", n_images=4, size=96)
    out_json, out_png = tmp_path / "rows.json", tmp_path / "sizes.png"
    assert gap.main(["--gt", str(ann), "--checkpoint", str(NANO), "--input-sizes", "64", "128",
                     "--json", str(out_json), "--plot", str(out_png)]) == 0
    rows = json.loads(out_json.read_text())
    assert [r["img_size"] for r in rows] == [64, 128]
    assert [r["adaptation"] for r in rows] == ["input 64 px", "input 128 px"]
    for r in rows:
        assert all(0.0 <= r[k] <= 1.0 for k in ("crater_recall@5", "rock_recall@5", "crater_AP50"))
    assert out_png.stat().st_size > 1000
    assert "| input 128 px |" in capsys.readouterr().out
    # not a multiple of the network's stride: one line, exit 2, no rows file
    bad_json = tmp_path / "bad.json"
    assert gap.main(["--gt", str(ann), "--checkpoint", str(NANO), "--input-sizes", "100",
                     "--json", str(bad_json)]) == 2
    assert "img_size" in capsys.readouterr().err and not bad_json.exists()
