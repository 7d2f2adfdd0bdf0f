"""The command line: every subcommand has --help; bad input is one line on stderr, exit 2."""

import subprocess
import sys

import pytest

from lunarnav_ml.cli import build_parser, main

SUBCOMMANDS = ("synth", "train", "eval", "export", "detect", "demo")


def test_every_subcommand_is_registered():
    parser = build_parser()
    choices = parser._subparsers._group_actions[0].choices  # noqa: SLF001
    for name in SUBCOMMANDS:
        assert name in choices


@pytest.mark.parametrize("name", SUBCOMMANDS)
def test_help(name, capsys):
    with pytest.raises(SystemExit) as exc:
        main([name, "--help"])
    assert exc.value.code == 0
    assert "usage: lunarnav" in capsys.readouterr().out


def test_missing_file_is_one_line_exit_2(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "lunarnav_ml.cli", "eval", "--gt", str(tmp_path / "nope.json"),
         "--threshold", "0.5", "--test-results", str(tmp_path / "r.json"),
         "--out", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "nope.json" in lines[0] and "Traceback" not in proc.stderr
    assert not (tmp_path / "o").exists()


def test_corrupt_json_names_the_file(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    proc = subprocess.run(
        [sys.executable, "-m", "lunarnav_ml.cli", "eval", "--gt", str(bad), "--threshold", "0.5",
         "--test-results", str(bad), "--out", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2 and "bad.json" in proc.stderr and "Traceback" not in proc.stderr
