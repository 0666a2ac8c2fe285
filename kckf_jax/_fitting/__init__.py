"""Fitting: the losses and the one optax training loop."""
