"""Training and fitting: the learned models, the static scene model, the profile's tuned parameters, the vendored data and scene files."""
