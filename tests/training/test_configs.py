"""Every YAML config instantiates; the CPU config trains a fast_dev_run through the CLI."""

from pathlib import Path

import pytest
import torch

from lunarnav_ml.data.datamodule import DetectionDataModule
from lunarnav_ml.training.lightning_cli import run_cli
from lunarnav_ml.training.module import DetectorModule

CONFIGS = [pytest.param(c, id=c.stem, marks=[pytest.mark.slow] if "yolov4" in c.stem else [])
           for c in sorted((Path(__file__).parents[2] / "configs").glob("*.yaml"))]


def _data_args(coco):
    return ["--data.train", str(coco["train"]), "--data.val", str(coco["val"])]


@pytest.mark.parametrize("config", CONFIGS)  # the full YOLOv4 one (64 M params) is slow
def test_every_config_instantiates(config, tiny_coco, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # runs/ folders land in the temporary directory
    args = ["--config", str(config), *_data_args(tiny_coco), "--data.num_workers", "0",
            "--trainer.accelerator", "cpu", "--trainer.devices", "1",
            "--trainer.strategy", "auto", "--trainer.precision", "32",
            "--trainer.sync_batchnorm", "false"]
    cli = run_cli(args, run=False)
    assert isinstance(cli.model, DetectorModule) and isinstance(cli.datamodule,
                                                                 DetectionDataModule)
    assert cli.model.hparams.img_size == cli.datamodule.img_size
    assert cli.model.hparams.class_names == ["crater", "rock", "artifact"]  # kept in checkpoints


def test_cli_fast_dev_run(tiny_coco, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    config = Path(__file__).parents[2] / "configs" / "nano_cpu.yaml"
    run_cli(["fit", "--config", str(config), *_data_args(tiny_coco), "--data.img_size", "64",
             "--data.batch_size", "4", "--trainer.fast_dev_run", "2",
             "--trainer.enable_progress_bar", "false"])
    assert (tmp_path / "runs" / "nano_cpu").is_dir()


def test_cli_bf16_mixed_on_cpu(tiny_coco, tmp_path, monkeypatch):
    """bf16 autocast (1.8x faster training on CPUs with AVX512-BF16, BENCHMARKS.md) runs
    through train.py with finite losses."""
    monkeypatch.chdir(tmp_path)
    config = Path(__file__).parents[2] / "configs" / "small_cpu.yaml"
    cli = run_cli(["fit", "--config", str(config), *_data_args(tiny_coco), "--data.img_size", "64",
                   "--data.batch_size", "4", "--trainer.fast_dev_run", "2",
                   "--trainer.precision", "bf16-mixed", "--trainer.enable_progress_bar", "false"])
    assert cli.trainer.precision == "bf16-mixed"
    loss = cli.trainer.callback_metrics["train/loss"]
    assert torch.isfinite(loss)


def test_train_py_reports_bad_input_in_one_line(tiny_coco, tmp_path, monkeypatch, capsys):
    import json

    from lunarnav_ml.training.lightning_cli import main

    monkeypatch.chdir(tmp_path)
    coco = json.loads(Path(tiny_coco["train"]).read_text())
    coco["annotations"][0]["bbox"][2] = 0.0
    bad = Path(tiny_coco["train"]).with_name("bad.json")
    bad.write_text(json.dumps(coco))
    config = Path(__file__).parents[2] / "configs" / "nano_cpu.yaml"
    code = main(["fit", "--config", str(config), "--data.train", str(bad), "--data.val",
                 str(tiny_coco["val"]), "--data.img_size", "64", "--trainer.fast_dev_run", "1",
                 "--trainer.enable_progress_bar", "false"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert err[-1].startswith("train.py: error: ") and "bad.json" in err[-1] and "bbox" in err[-1]
    assert not any("Traceback" in line for line in err)


@pytest.mark.parametrize("flag", ["--config", "-c", "--config="])
def test_train_py_reports_a_malformed_config_in_one_line(tmp_path, capsys, flag):
    from lunarnav_ml.training.lightning_cli import main

    bad = tmp_path / "bad.yaml"
    bad.write_text("model:\n  preset: [nano\ndata: {}\n")
    args = ["fit", flag + str(bad)] if flag.endswith("=") else ["fit", flag, str(bad)]
    code = main(args)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert err[0].startswith(f"train.py: error: {bad}: not valid YAML")


def test_bad_preset_and_loader_settings_are_config_errors(tiny_coco, tmp_path, monkeypatch):
    from lunarnav_ml.errors import ConfigError

    monkeypatch.chdir(tmp_path)
    for extra, message in ((["--model.preset", "huge"], "unknown model preset 'huge'"),
                           (["--data.img_size", "0"], "data.img_size: must be a positive"),
                           (["--data.batch_size", "0"], "data.batch_size: must be an integer"),
                           (["--data.num_workers", "-1"], "data.num_workers: must be an")):
        with pytest.raises(ConfigError, match=message):
            run_cli([*_data_args(tiny_coco), "--trainer.accelerator", "cpu", *extra], run=False)


def test_train_py_checks_ckpt_path_before_lightning_loads_it(tiny_coco, tmp_path, monkeypatch,
                                                           capsys):
    from lunarnav_ml.models import build_model
    from lunarnav_ml.training.checkpoint import save_slim
    from lunarnav_ml.training.lightning_cli import main

    monkeypatch.chdir(tmp_path)
    trunc = tmp_path / "trunc.ckpt"
    torch.save({"state_dict": {}, "hyper_parameters": {}}, trunc)
    trunc.write_bytes(trunc.read_bytes()[:100])
    slim = save_slim(tmp_path / "slim.pt", {"preset": "nano"}, build_model("nano"))
    config = tmp_path / "resume.yaml"
    config.write_text(f"ckpt_path: {trunc}\n")
    for args, message in (
            (["--ckpt_path", str(trunc)], f"{trunc}: not a readable checkpoint"),
            ([f"--ckpt_path={tmp_path / 'nope.ckpt'}"], f"{tmp_path / 'nope.ckpt'}: checkpoint not"),
            (["--config", str(config)], f"{trunc}: not a readable checkpoint"),
            (["--ckpt_path", str(slim)], f"{slim}: not a Lightning training checkpoint")):
        code = main(["fit", *_data_args(tiny_coco), "--trainer.accelerator", "cpu", *args])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1 and err[0].startswith(f"train.py: error: {message}")


def test_default_root_dir_moves_the_run_folder(tiny_coco, tmp_path, monkeypatch):
    """--trainer.default_root_dir on the command line moves the config's logger and checkpoint
    folders with it; without it they stay where the config puts them."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    monkeypatch.chdir(tmp_path)
    config = Path(__file__).parents[2] / "configs" / "small_relu_lowlr.yaml"
    args = ["--config", str(config), *_data_args(tiny_coco), "--data.num_workers", "0"]

    def folders(cli):
        dirs = {Path(cb.dirpath).relative_to(tmp_path.resolve()).as_posix()
                for cb in cli.trainer.callbacks if isinstance(cb, ModelCheckpoint)}
        return {Path(cli.trainer.loggers[0].save_dir).as_posix()}, dirs

    logs, ckpts = folders(run_cli(args, run=False))
    assert logs == {"runs/small_relu_lowlr"}
    assert ckpts == {"runs/small_relu_lowlr/checkpoints", "runs/small_relu_lowlr/snapshots"}
    cli = run_cli([*args, "--trainer.default_root_dir", "runs/again"], run=False)
    logs, ckpts = folders(cli)
    assert logs == {"runs/again"}
    assert ckpts == {"runs/again/checkpoints", "runs/again/snapshots"}
    assert cli.trainer.default_root_dir == "runs/again"


def test_moved_path_keeps_paths_outside_the_root():
    from lunarnav_ml.training.lightning_cli import moved_path

    assert moved_path("runs/a/checkpoints", "runs/a", "runs/b") == "runs/b/checkpoints"
    assert moved_path("runs/a", "runs/a/", "out/b") == "out/b"
    assert moved_path("runs/ab/checkpoints", "runs/a", "runs/b") == "runs/ab/checkpoints"
    assert moved_path("/elsewhere/logs", "runs/a", "runs/b") == "/elsewhere/logs"
