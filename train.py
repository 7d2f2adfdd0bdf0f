"""Train the crater detector with Lightning: ``python train.py fit --config configs/nano_cpu.yaml``.

Subcommands and options are LightningCLI's (``fit``, ``validate``, ``--ckpt_path`` to resume,
``--print_config``); see :mod:`lunarnav_ml.training.lightning_cli`. Bad input (a missing or
malformed dataset, a bad checkpoint) ends with one line naming it and exit status 2.
"""

import sys

from lunarnav_ml.training.lightning_cli import main

if __name__ == "__main__":
    sys.exit(main())
