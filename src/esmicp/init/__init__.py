"""Global initialisation: coarse poses from local shape features (no initial guess needed)."""
