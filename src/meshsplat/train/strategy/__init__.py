"""train/strategy."""
