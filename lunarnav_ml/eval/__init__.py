"""lunarnav_ml.eval."""
