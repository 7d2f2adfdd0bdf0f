"""The LightningCLI behind ``train.py`` and ``lunarnav train``: YAML configs map onto
:class:`DetectorModule`, :class:`DetectionDataModule` and the Lightning ``Trainer``.

Examples::

    python train.py fit --config configs/nano_cpu.yaml
    python train.py fit --config configs/nano_cpu.yaml --ckpt_path runs/nano_cpu/checkpoints/last.ckpt
    python train.py fit --config configs/finetune_real.yaml --model.init_from best.ckpt
    python train.py fit --config configs/small_relu_lowlr.yaml --model.init_from small.pt \
        --trainer.default_root_dir runs/lowlr_again   # logs and checkpoints there too
"""

from __future__ import annotations

import os
import sys
import warnings
from collections.abc import Sequence

from lightning.pytorch.cli import LightningCLI

from lunarnav_ml.data.datamodule import DetectionDataModule
from lunarnav_ml.errors import REPORTED_ERRORS, InputError
from lunarnav_ml.training.checkpoint import load_checkpoint_file
from lunarnav_ml.training.module import DetectorModule
from lunarnav_ml.utils.yamlfile import read_yaml


class DetectorCLI(LightningCLI):
    """LightningCLI that keeps the input size of model and data in step, and moves a config's
    run folder with ``--trainer.default_root_dir``: the loggers' ``save_dir`` and the
    checkpoint callbacks' ``dirpath`` under the config's ``default_root_dir`` follow the new
    one, so a config continued by command-line overrides writes a run folder of its own."""

    def __init__(self, *args, moved_root: tuple[str, str] | None = None, **kwargs) -> None:
        self.moved_root = moved_root  # (the config files' default_root_dir, the command line's)
        super().__init__(*args, **kwargs)

    def add_arguments_to_parser(self, parser) -> None:
        parser.link_arguments("data.img_size", "model.img_size")
        parser.link_arguments("data.num_classes", "model.num_classes")

    def before_instantiate_classes(self) -> None:
        if self.moved_root is None:
            return
        config = self.config[self.subcommand] if self.subcommand else self.config
        trainer = config.get("trainer")
        if trainer is None:
            return
        loggers = trainer.get("logger")
        for entry in [*(loggers if isinstance(loggers, list) else [loggers]),
                      *(trainer.get("callbacks") or [])]:
            init_args = getattr(entry, "init_args", None)
            for key in ("save_dir", "dirpath"):
                value = getattr(init_args, key, None) if init_args is not None else None
                if isinstance(value, str):
                    setattr(init_args, key, moved_path(value, *self.moved_root))


def moved_path(path: str, old_root: str, new_root: str) -> str:
    """``path`` with its leading ``old_root`` replaced by ``new_root``; other paths as given."""
    rel = os.path.relpath(os.path.normpath(path), os.path.normpath(old_root))
    if rel == os.curdir:
        return new_root
    if rel == os.pardir or rel.startswith(os.pardir + os.sep):  # outside the old root
        return path
    return os.path.join(new_root, rel)


def run_cli(args: Sequence[str] | None = None, run: bool = True, prog: str | None = None
            ) -> DetectorCLI:
    """Parse ``args`` (default: ``sys.argv``) and run the chosen Lightning subcommand."""
    # ``lunarnav train`` passes its own arguments on purpose; Lightning warns about that.
    warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
    argv = sys.argv[1:] if args is None else args
    configs = [read_yaml(path, "config file")  # one-line ConfigError for a missing or
               for path in config_files(argv)]  # malformed file
    ckpt = option_value(argv, "--ckpt_path")
    if ckpt is None:
        ckpt = config_value(configs, "ckpt_path")
    if ckpt is not None:
        check_ckpt_path(str(ckpt))
    root = option_value(argv, "--trainer.default_root_dir")
    config_root = config_value(configs, "trainer", "default_root_dir")
    moved = ((str(config_root), root) if root is not None and config_root is not None
             else None)
    return DetectorCLI(DetectorModule, DetectionDataModule, args=list(args) if args is not None
                       else None, run=run, seed_everything_default=0,
                       save_config_kwargs={"overwrite": True},
                       parser_kwargs={"prog": prog} if prog else None, moved_root=moved)


def config_value(configs: Sequence[object], *keys: str) -> object | None:
    """The value at ``keys`` in the last config file that sets it (not null), as jsonargparse
    merges them; None where none does."""
    for config in reversed(configs):
        for key in keys:
            config = config.get(key) if isinstance(config, dict) else None
        if config is not None:
            return config
    return None


def option_value(args: Sequence[str], name: str) -> str | None:
    """The last value given to option ``name`` (``name VALUE`` or ``name=VALUE``), or None."""
    value = None
    for k, arg in enumerate(args):
        if arg == name and k + 1 < len(args):
            value = args[k + 1]
        elif arg.startswith(f"{name}="):
            value = arg.split("=", 1)[1]
    return value


def check_ckpt_path(path: str) -> None:
    """One-line InputError for a ``--ckpt_path`` that is missing or not a readable checkpoint,
    before Lightning loads it (Lightning's own names such as ``last`` pass)."""
    if str(path) in ("null", "last", "best", "hpc") or str(path).startswith("registry"):
        return
    ckpt = load_checkpoint_file(path)
    if not isinstance(ckpt, dict) or "pytorch-lightning_version" not in ckpt:
        raise InputError(f"{path}: not a Lightning training checkpoint, so it cannot resume a "
                         "run; start from its weights with --model.init_from")


def config_files(args: Sequence[str]) -> list[str]:
    """The files given to ``--config`` / ``-c`` (``--config=FILE`` too) in CLI arguments."""
    files = []
    for k, arg in enumerate(args):
        if arg in ("--config", "-c") and k + 1 < len(args):
            files.append(args[k + 1])
        elif arg.startswith("--config="):
            files.append(arg.split("=", 1)[1])
    return files


def main(args: Sequence[str] | None = None) -> int:
    """``train.py``: :func:`run_cli` with bad input reported in one line (exit status 2)."""
    try:
        run_cli(args)
    except REPORTED_ERRORS as err:
        print(f"train.py: error: {err}", file=sys.stderr)
        return 2
    return 0
