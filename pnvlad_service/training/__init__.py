"""Training the encoder: configuration, losses, hard-negative mining, checkpoints, the loop."""
