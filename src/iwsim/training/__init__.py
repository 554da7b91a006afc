"""One generic training loop, checkpoints and distributed helpers, shared by every stage."""
