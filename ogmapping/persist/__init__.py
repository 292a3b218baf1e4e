"""A map kept or moved: its state as plain tensors, snapshots, and the optimisation's training state."""
