import json

import numpy as np
import pytest

from tests.bench_scripts import load_script

study = load_script("crest_rule_study")


def _cand(search, rule, ok=True, x=10.0, d=5.0, resid=0.3, disp=10.0):
    return {"search": search, "rule": rule, "ok": ok, "center_m": [x, 0.0] if ok else None,
            "diameter_m": d if ok else None, "rim_residual_px": resid, "rim_disparity_px": disp}


def test_rules_pick_from_the_first_search_with_a_passing_lift():
    cands = [_cand(6, "largest", ok=False), _cand(6, "lowest", ok=False),
             _cand(12, "largest", x=10.0), _cand(12, "lowest", x=10.4)]
    assert study.RULES["farther (sessions 33-66)"](cands)["center_m"] == [10.4, 0.0]
    assert study.RULES["nearer"](cands)["center_m"] == [10.0, 0.0]
    assert study.RULES["largest first"](cands)["rule"] == "largest"
    assert study.RULES["mean of the passing"](cands)["center_m"] == pytest.approx([10.2, 0.0])
    # the first search wins even where a later one would read farther
    first = [_cand(6, "largest", x=9.0), _cand(6, "lowest", ok=False), _cand(12, "lowest", x=11)]
    assert study.RULES["farther (sessions 33-66)"](first)["center_m"] == [9.0, 0.0]
    assert study.RULES["lowest first"](first)["center_m"] == [9.0, 0.0]  # the one that passed
    assert study.RULES["lowest only"](first)["center_m"] == [11.0, 0.0]
    assert study.RULES["farther (sessions 33-66)"]([_cand(6, "largest", ok=False)]) is None


def test_the_disagreement_gate_and_the_gated_mean():
    close = [_cand(6, "largest", x=10.0), _cand(6, "lowest", x=10.2)]  # 0.08 radii apart
    apart = [_cand(6, "largest", x=10.0), _cand(6, "lowest", x=11.0)]  # 0.4 radii
    gate = study.RULES["farther, none where they differ by > 0.1 r"]
    assert gate(close)["center_m"] == [10.2, 0.0] and gate(apart) is None
    mean = study.RULES["mean within 0.25 r, else farther"]
    assert mean(close)["center_m"] == pytest.approx([10.1, 0.0])
    assert mean(apart)["center_m"] == [11.0, 0.0]
    today = study.RULES["mean within 2 % of the range, else farther (today)"]  # 2 % of 10.2 m
    assert today(close)["center_m"] == pytest.approx([10.1, 0.0])
    assert today([_cand(6, "largest", x=10.0), _cand(6, "lowest", x=10.3)])["center_m"] == [
        10.3, 0.0]


def _crater(d, near, along, bearing=0.3):
    """A candidate row whose two lifts (both rules) lie ``along`` m beyond the truth on the
    line of sight."""
    rho = near + d / 2
    u = np.array([np.cos(bearing), np.sin(bearing)])
    at = {"center_m": ((rho + along) * u).tolist()}
    return {"ann_id": 1, "image_id": 1, "diameter_m": d, "near_rim_range_m": near,
            "truth_center_m": [*(rho * u), 0.0], "camera_height_m": 1.5,
            "candidates": [_cand(6, rule, d=d) | at for rule in ("largest", "lowest")]}


def test_a_calibrated_offset_takes_out_a_known_edge_offset():
    """Lifts read too far by what an edge 0.2 m + 0.05 r in front of the crest causes: the
    offsets fitted on them, moved back, leave no error."""
    rows = []
    for d in (5.0, 10.0, 15.0, 20.0):
        for near in np.linspace(5.0, 20.0, 61):
            rho = near + d / 2
            rows.append(_crater(d, near, (0.2 + 0.05 * d / 2) / (1 - d / 2 / rho)))
    picked = [study._report_row(r, study.RULES["farther (sessions 33-66)"](r["candidates"])) for r in rows]
    radius, near, need, height = study.needed_offsets(picked)
    terms = study.fit_offset(radius, near, need, height)[:3]
    assert terms == pytest.approx((-0.2, -0.05, 0.0), abs=1e-6)
    moved = study._with_offset(picked, terms)
    assert max(r["center_err_m"] for r in moved) < 1e-6
    assert min(r["center_err_m"] for r in picked) > 0.2


def test_compare_prints_a_row_per_rule(capsys):
    sets = []
    for seed in (0, 1):
        rng = np.random.default_rng(seed)
        sets.append([_crater(d, near, 0.3 + rng.normal(0, 0.05))
                     for d in (5.0, 10.0) for near in np.linspace(5.0, 20.0, 61)])
    study.compare(sets, held_out=1)
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 1 + len(study.RULES)
    assert out[1].startswith("mean within 2 % of the range, else farther (today) | ")
    # a fold's offsets absorb the common 0.3 m: what is left is the noise
    assert float(out[1].split(" | ")[1].split(" / ")[0]) < 0.5


def test_errors_are_one_line(capsys, tmp_path):
    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "candidates.json").write_text(json.dumps({"not": "a list"}))
    argv = [str(tmp_path / "a" / "ann.json"), str(tmp_path / "b" / "ann.json"),
            "--out", str(tmp_path), "--rows-only"]
    assert study.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("crest_rule_study: error:") and "candidates" in err and "\n" not in err
