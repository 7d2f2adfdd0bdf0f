"""Train the crater detector with Lightning: ``python train.py fit --config configs/nano_cpu.yaml``.

Subcommands and options are LightningCLI's (``fit``, ``validate``, ``--ckpt_path`` to resume,
``--print_config``); see :mod:`lunarnav_ml.training.lightning_cli`.
"""

from lunarnav_ml.training.lightning_cli import run_cli

if __name__ == "__main__":
    run_cli()
