"""Training: the one step loop over a data source, and what watches it (docs/methods.md, "Training loop")."""
