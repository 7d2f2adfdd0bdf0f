"""The real-data training recipes (configs/real/*.yaml).

A fast static check runs by default: every ``model`` / ``data`` key is an ``__init__`` argument
of ``DetectorModule`` / ``DetectionDataModule`` (read with ``ast``: importing Lightning takes
~12 s on two CPU cores). The full LightningCLI instantiation is marked slow (``-m slow``).
"""

import ast
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).parents[2]
CONFIGS = sorted((ROOT / "configs" / "real").glob("*.yaml"))
IDS = [c.stem for c in CONFIGS]


def _init_args(source: Path, cls: str) -> set[str]:
    tree = ast.parse(source.read_text())
    node = next(n for n in ast.walk(tree) if isinstance(n, ast.ClassDef) and n.name == cls)
    init = next(n for n in node.body if isinstance(n, ast.FunctionDef) and n.name == "__init__")
    return {a.arg for a in init.args.args[1:] + init.args.kwonlyargs}


def _section(config: Path, value):
    """A section given inline, or as a path relative to the config file."""
    return yaml.safe_load((config.parent / value).read_text()) if isinstance(value, str) else value


def test_the_three_recipes_exist():
    assert IDS == ["finetune", "mixed", "real_only"]


@pytest.mark.parametrize("config", CONFIGS, ids=IDS)
def test_recipe_keys_are_constructor_arguments(config):
    cfg = yaml.safe_load(config.read_text())
    model, data = _section(config, cfg["model"]), _section(config, cfg["data"])
    assert set(model) <= _init_args(ROOT / "lunarnav_ml/training/module.py", "DetectorModule")
    assert set(data) <= _init_args(ROOT / "lunarnav_ml/data/datamodule.py", "DetectionDataModule")
    train = data["train"] if isinstance(data["train"], list) else [data["train"]]
    assert "data/real/chandai_v5/train/annotations.json" in train
    assert data["val"] == "data/real/chandai_v5/valid/annotations.json"
    assert len(data.get("weights") or train) == len(train)
    assert cfg["trainer"]["default_root_dir"] == f"runs/real_{config.stem.replace('real_', '')}"


@pytest.mark.slow
@pytest.mark.parametrize("config", CONFIGS, ids=IDS)
def test_recipe_instantiates(config, tmp_path, monkeypatch):
    from lunarnav_ml.training.lightning_cli import run_cli

    monkeypatch.chdir(tmp_path)  # nothing is read or written before fit
    cli = run_cli(["--config", str(config)], run=False)
    data = cli.datamodule
    assert cli.model.hparams.img_size == data.img_size
    if config.stem == "finetune":
        assert cli.model.hparams.init_from and not cli.model.hparams.freeze_backbone
    if config.stem == "mixed":
        assert len(data.train_files) == 2 and data.weights == [0.7, 0.3]
    if config.stem == "real_only":
        assert cli.model.hparams.init_from is None and len(data.train_files) == 1
