"""lunarnav_ml.baselines."""
