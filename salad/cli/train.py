"""`salad train`: the VAE, the denoiser, its consistency-distilled student, the evaluator or the classifier;
`salad average`: the weight-by-weight mean of fine-tunes of one denoiser or student."""
from __future__ import annotations


def cmd_train(a) -> int:
    from ..config import apply_overrides, load_toml
    from ..training.configs import ConsistencyTrainConfig, DenoiserTrainConfig, VAETrainConfig
    from ..training.loop import Trainer
    if a.continue_from and a.what not in ("vae", "denoiser", "consistency"):
        raise ValueError(f"--continue-from applies to the vae, the denoiser and consistency, not to {a.what}")
    if a.init_from and a.what not in ("vae", "vae-san", "denoiser", "consistency"):
        raise ValueError(f"--init-from applies to the vae, vae-san, the denoiser and consistency, not to {a.what}")
    if a.new_latents and (a.what != "denoiser" or not (a.init_from or a.continue_from)):
        raise ValueError("--new-latents applies to a denoiser started with --init-from or --continue-from")
    if a.validate_only and (a.what != "denoiser" or not a.init_from):
        raise ValueError("--validate-only applies to a denoiser given with --init-from")
    if a.balance is not None and a.what not in ("vae", "vae-san", "denoiser", "consistency"):
        raise ValueError(f"--balance applies to the vae, vae-san, the denoiser and consistency, not to {a.what} "
                         "(whose config's data.balance means something else)")
    if a.teacher and a.what != "consistency":
        raise ValueError(f"--teacher applies to consistency distillation, not to {a.what}")
    if a.what == "vae":
        from ..training.vae_task import VAETask
        cfg = load_toml(VAETrainConfig, a.config)
        apply_overrides(cfg, a)
        _limit_threads(cfg)
        task, ema = VAETask(cfg), None
    elif a.what == "denoiser":
        from ..training.denoiser_task import DenoiserTask
        cfg = load_toml(DenoiserTrainConfig, a.config)
        apply_overrides(cfg, a)
        if a.validate_only:
            cfg.data.bundle = ""      # a latent bundle holds the training split alone; validation reads data.root
        _limit_threads(cfg)
        task, ema = DenoiserTask(cfg, encode_text=not a.validate_only), cfg.ema_decay
        task.new_latents = a.new_latents
    elif a.what == "consistency":
        from ..training.consistency_task import ConsistencyTask
        cfg = load_toml(ConsistencyTrainConfig, a.config)
        apply_overrides(cfg, a)
        if a.teacher:
            cfg.teacher = a.teacher
        _limit_threads(cfg)
        task, ema = ConsistencyTask(cfg), None      # the task keeps its own EMA: the target network
    elif a.what == "vae-san":
        from ..training.vae_adv_task import train_vae_san
        return train_vae_san(a)
    elif a.what == "classifier":
        from ..training.classifier_task import train_classifier
        return train_classifier(a)
    else:
        from ..training.evaluator_task import train_evaluator
        return train_evaluator(a)
    trainer = Trainer(task, cfg.optim, cfg.run, ema_decay=ema)
    if a.validate_only:
        return _print_validation_loss(task, trainer, a.init_from)
    if a.init_from or a.continue_from:
        trainer.init_weights(a.init_from or a.continue_from, carry_step=bool(a.continue_from))
    out = trainer.fit()
    print(f"model written to {out}")
    return 0


def _print_validation_loss(task, trainer, model_dir: str) -> int:
    import json
    from pathlib import Path
    task.load_weights(trainer.ema or trainer.model, Path(model_dir))
    loss = trainer.validate()
    print(json.dumps({"model": model_dir, "val_loss": round(loss, 6)}))
    return 0


def _limit_threads(cfg) -> None:
    """run.threads from the start: the tasks encode captions and cache latents before the loop starts."""
    if cfg.run.threads:
        import torch
        torch.set_num_threads(cfg.run.threads)


def add_parser(sub) -> None:
    t = sub.add_parser("train", help="train the VAE, the denoiser, its consistency student, the evaluator or the "
                                     "classifier",
                       epilog="--init-from and --continue-from are ignored when the run's out_dir holds a saved "
                              "state: the run resumes from it.")
    t.add_argument("what", choices=("vae", "vae-san", "denoiser", "consistency", "evaluator", "classifier"))
    t.add_argument("--config", required=True, help="TOML config file")
    t.add_argument("--out-dir", help="override run.out_dir")
    t.add_argument("--data", help="override data.root")
    t.add_argument("--bundle", help="denoiser, consistency: override data.bundle, a latent bundle (salad data bundle) "
                                    "to train from instead of the dataset")
    t.add_argument("--max-steps", type=int, help="override optim.max_steps")
    t.add_argument("--balance", type=float,
                   help="vae, vae-san, denoiser, consistency: override data.balance, how often each content class is "
                        "drawn, as (its clip count)^balance: 1 as recorded, 0 every class alike, down to -1 the rarer "
                        "classes more often")
    t.add_argument("--threads", type=int, help="override run.threads (CPU threads for this process)")
    t.add_argument("--seed", type=int, help="override run.seed (the batches' draw and the initial weights): runs of "
                                            "one recipe with other seeds, e.g. to average them (salad average)")
    t.add_argument("--device", help="override run.device: auto (default: a CUDA GPU when torch sees one, else the "
                                    "CPU), cpu, cuda or cuda:N; under torchrun each process takes its LOCAL_RANK's GPU")
    t.add_argument("--vae", help="denoiser: override vae (the VAE whose latents it learns), e.g. assets/model/vae")
    t.add_argument("--teacher", metavar="MODEL_DIR",
                   help="consistency: override teacher, the model directory (vae/ + denoiser/) to distil")
    start = t.add_mutually_exclusive_group()
    start.add_argument("--init-from", metavar="MODEL_DIR",
                       help="fine-tune: start a new run (step 0) from an exported model's weights; consistency: "
                            "a student, also one of an earlier teacher (e.g. before the teacher's fine-tune)")
    start.add_argument("--continue-from", metavar="MODEL_DIR",
                       help="train an exported model further: its weights and step count, so the LR schedule and "
                            "max_steps count on from its step; the fresh optimiser warms up again over warmup_steps. "
                            "consistency: an exported student of the same teacher")
    t.add_argument("--validate-only", action="store_true",
                   help="denoiser: print the --init-from model's loss on the validation split (what run.validate_every "
                        "logs during training) and stop, so that snapshots of runs with other recipes compare")
    t.add_argument("--new-latents", action="store_true",
                   help="denoiser: let --init-from / --continue-from start from a denoiser trained on another VAE's "
                        "latents (e.g. before the VAE's encoder was retrained); it then re-learns this VAE's latents")
    t.set_defaults(func=cmd_train)


def cmd_average(a) -> int:
    from ..training.average import average_checkpoints
    out = average_checkpoints(a.checkpoints, a.weights, a.out)
    print(f"average written to {out}")
    return 0


def add_average_parser(sub) -> None:
    v = sub.add_parser("average", help="the weight-by-weight mean of denoisers or consistency students fine-tuned "
                                       "from one start (a \"model soup\")",
                       epilog="The checkpoints must share their architecture, text features and VAE, and students "
                              "their teacher and guidance range. The average records its inputs (path, weight, step, "
                              "SHA-256) under meta.average; a student's meta.consistency.default_for is not carried "
                              "over: measure the average first.")
    v.add_argument("checkpoints", nargs="+", metavar="CHECKPOINT",
                   help="checkpoint directories, e.g. assets/model/consistency or runs/NAME/model")
    v.add_argument("--weights", type=float, nargs="+", metavar="W",
                   help="one weight per checkpoint, in [0, 1], summing to 1 (default: equal)")
    v.add_argument("--out", required=True, help="directory to write the average to (replaced atomically)")
    v.set_defaults(func=cmd_average)
