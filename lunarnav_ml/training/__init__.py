"""LightningModule, training API, checkpoints, and the ``lunarnav train`` / ``detect`` commands."""
