"""Training: the config, the loop, its tasks, evaluation, checkpoints, metrics and plots."""
