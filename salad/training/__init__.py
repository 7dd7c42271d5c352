"""Training: configs, the shared loop (checkpointing, resume, DDP) and the per-model tasks, the
evaluator's and the classifier's included."""
