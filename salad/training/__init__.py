"""Training: configs, the shared loop (checkpointing, resume, DDP) and the per-model tasks."""
