"""The training loop shared by every model: AdamW with warm-up and step decay, optional
bf16 autocast, EMA, tqdm progress, periodic atomic checkpoints with exact resume, on the CPU
or a CUDA GPU, and multi-process data parallelism through torch.distributed (launched by
torchrun: gloo between CPU processes, NCCL between GPUs, one GPU per process)."""
from __future__ import annotations

import copy
import json
import os
import random
import sys
import time
from contextlib import nullcontext
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import torch
import torch.distributed as dist
from tqdm import tqdm

from ..checkpoint import CheckpointError, load_checkpoint, load_state_strict, recover_checkpoint, save_checkpoint
from ..config import defaults_of, training_identity, validate
from ..files import atomic_write_text
from ..precision import bf16_supported, resolve_device, to_device
from .configs import OptimConfig, RunConfig

STATE_DIR = "state"


class Task(Protocol):
    """What the loop needs from a model-specific task."""

    model: torch.nn.Module
    kind: str

    def batch(self, rng: np.random.Generator) -> dict: ...
    def loss(self, model: torch.nn.Module, batch: dict) -> tuple[torch.Tensor, dict[str, float]]: ...
    def export(self, model: torch.nn.Module, path: Path, meta: dict[str, Any]) -> None: ...
    def config_dict(self) -> dict: ...
    # optional, for --init-from / --continue-from (continuing=True); returns the exported model's meta
    # (step, samples_seen):
    # def load_weights(self, model: torch.nn.Module, path: Path, continuing: bool) -> dict
    # optional, for run.validate_every: the model's loss on fixed held-out batches (None: none to give)
    # def validation_loss(self, model: torch.nn.Module) -> float | None
    # optional, state of the task's own that a resume needs (saved with the training state), and its restore:
    # def training_state(self) -> tuple[dict[str, torch.Tensor], dict]
    # def restore_training_state(self, tensors: dict[str, torch.Tensor], doc: dict) -> None


def lr_factor(step: int, cfg: OptimConfig, warm_from: int = 0) -> float:
    """warm_from: the step a warm start began at; its fresh optimiser warms up again from there."""
    warm = min(1.0, (step - warm_from + 1) / cfg.warmup_steps) if cfg.warmup_steps > 0 else 1.0
    return warm * cfg.gamma ** sum(step >= m for m in cfg.milestones)


def training_device(name: str) -> torch.device:
    """The run's device; under torchrun each process takes the GPU of its LOCAL_RANK."""
    device = resolve_device(name)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    if device.type == "cuda":
        torch.cuda.set_device(device)
    return device


def distributed_context(device: torch.device | None = None) -> tuple[int, int]:
    """(rank, world size); joins the process group when launched by torchrun."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("nccl" if device is not None and device.type == "cuda" else "gloo")
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _flatten_optimizer(state: dict) -> tuple[dict[str, torch.Tensor], dict]:
    tensors, scalars = {}, {}
    for pid, entry in state["state"].items():
        for key, value in entry.items():
            if isinstance(value, torch.Tensor):
                tensors[f"{pid}.{key}"] = value
            else:
                scalars[f"{pid}.{key}"] = value
    return tensors, {"param_groups": state["param_groups"], "scalars": scalars}


def _unflatten_optimizer(tensors: dict[str, torch.Tensor], doc: dict) -> dict:
    state: dict[int, dict] = {}
    for flat, value in list(tensors.items()) + list(doc["scalars"].items()):
        pid, key = flat.split(".", 1)
        state.setdefault(int(pid), {})[key] = value
    return {"state": state, "param_groups": doc["param_groups"]}


def _differences(mine: dict, theirs: dict, prefix: str = "") -> list[tuple[str, Any, Any]]:
    """(dotted key, value here, value there) for every leaf on which two nested configs differ."""
    out = []
    for key in sorted(set(mine) | set(theirs)):
        a, b = mine.get(key), theirs.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            out += _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            out.append((f"{prefix}{key}", a, b))
    return out


class Trainer:
    def __init__(self, task: Task, optim: OptimConfig, run: RunConfig, ema_decay: float | None = None):
        validate(optim, "optim.")
        validate(run, "run.")
        self.task, self.optim_cfg, self.run_cfg = task, optim, run
        self.device = training_device(run.device)
        self.rank, self.world = distributed_context(self.device)
        if run.threads:
            torch.set_num_threads(run.threads)
        self.out = Path(run.out_dir)
        self.model = task.model.to(self.device)
        self.ema = copy.deepcopy(self.model).eval().requires_grad_(False) if ema_decay else None
        self.ema_decay = ema_decay
        params = [p for p in self.model.parameters() if p.requires_grad]
        # fused: the default CPU implementation loops over the parameters in Python (20 of a 550 ms step
        # against 3 fused, session 71)
        self.fused_optimizer = True if self.device.type in ("cpu", "cuda") else None
        self.optimizer = torch.optim.AdamW(params, lr=optim.lr, betas=tuple(optim.betas),
                                           weight_decay=optim.weight_decay, fused=self.fused_optimizer)
        self.step_count = 0
        self.warm_from = 0
        self.rng = np.random.default_rng(run.seed + 1000 * self.rank)
        torch.manual_seed(run.seed + 1000 * self.rank)
        random.seed(run.seed + 1000 * self.rank)
        self.wrapped = self.model
        if self.world > 1:
            on_gpu = [self.device.index] if self.device.type == "cuda" else None
            self.wrapped = torch.nn.parallel.DistributedDataParallel(self.model, device_ids=on_gpu)
        self.samples_seen = 0
        self.bf16 = run.bf16 and bf16_supported(self.device)
        if run.bf16 and not self.bf16 and self.rank == 0:
            tqdm.write(f"run.bf16 is set but this {self.device.type.upper()} has no native bf16 (emulated it is "
                       "many times slower than fp32): training in fp32", file=sys.stderr)

    # ------------------------------------------------------------ one step
    def autocast(self):
        if self.bf16:
            return torch.autocast(self.device.type, dtype=torch.bfloat16)
        return nullcontext()

    def step(self, batch: dict) -> dict[str, float]:
        self.model.train()
        batch = to_device(batch, self.device)
        for g in self.optimizer.param_groups:
            g["lr"] = self.optim_cfg.lr * lr_factor(self.step_count, self.optim_cfg, self.warm_from)
        with self.autocast():
            loss, logs = self.task.loss(self.wrapped, batch)
        if not torch.isfinite(loss):
            raise FloatingPointError(f"loss became {float(loss)} at step {self.step_count}")
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.optim_cfg.grad_clip > 0:
            logs["grad_norm"] = float(torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.optim_cfg.grad_clip))
        self.optimizer.step()
        if self.ema is not None:
            with torch.no_grad():
                d = min(self.ema_decay, (1 + self.step_count) / (10 + self.step_count))
                # one fused call: a Python loop over the parameters dominated the step on a GPU
                torch._foreach_lerp_(list(self.ema.parameters()), list(self.model.parameters()), 1 - d)
        self.step_count += 1
        logs["lr"] = self.optimizer.param_groups[0]["lr"]
        return logs

    # ------------------------------------------------------------ state
    def save_state(self) -> None:
        if self.rank != 0:
            return
        opt_tensors, opt_doc = _flatten_optimizer(self.optimizer.state_dict())
        parts = {"model": self.model.state_dict(), "optimizer": opt_tensors,
                 "rng": {"torch": torch.get_rng_state()}}
        if self.device.type == "cuda":
            parts["rng"]["cuda"] = torch.cuda.get_rng_state(self.device)
        if self.ema is not None:
            parts["ema"] = self.ema.state_dict()
        meta = {"step": self.step_count, "optimizer": opt_doc, "numpy_rng": self.rng.bit_generator.state,
                "python_rng": json.loads(json.dumps(random.getstate())), "samples_seen": self.samples_seen,
                "warm_from": self.warm_from}
        if hasattr(self.task, "training_state"):
            parts["task"], meta["task"] = self.task.training_state()
        save_checkpoint(self.out / STATE_DIR, f"{self.task.kind}-train-state", self.task.config_dict(), parts, meta)

    def try_resume(self) -> bool:
        path = self.out / STATE_DIR
        if not recover_checkpoint(path):
            return False
        doc, parts = load_checkpoint(path, kind=f"{self.task.kind}-train-state")
        # anything that shapes the model, data or optimisation must match the run's (training_identity)
        mine = training_identity(json.loads(json.dumps(self.task.config_dict())))
        cfg = getattr(self.task, "cfg", None)
        theirs = training_identity(doc["config"], defaults_of(cfg))
        differences = _differences(mine, theirs)
        if differences:
            changed = sorted({key.split(".")[0] for key, _, _ in differences})
            details = "; ".join(f"{key} is {a!r} here, {b!r} in the run" for key, a, b in differences)
            raise CheckpointError(f"{path}: was trained with a different config (differs in {changed}: {details}); "
                                  "use a new out_dir or the same config")
        load_state_strict(self.model, parts["model"], str(path))
        if self.ema is not None and "ema" in parts:
            load_state_strict(self.ema, parts["ema"], str(path))
        meta = doc["meta"]
        self.optimizer.load_state_dict(_unflatten_optimizer(parts["optimizer"], meta["optimizer"]))
        for group in self.optimizer.param_groups:   # how a step is computed is not state: this build's way
            group["fused"] = self.fused_optimizer
        self.step_count = int(meta["step"])
        self.samples_seen = int(meta.get("samples_seen", 0))
        self.warm_from = int(meta.get("warm_from", 0))
        if self.rank == 0:
            torch.set_rng_state(parts["rng"]["torch"])
            if self.device.type == "cuda" and "cuda" in parts["rng"]:
                torch.cuda.set_rng_state(parts["rng"]["cuda"], self.device)
            self.rng.bit_generator.state = meta["numpy_rng"]
            state = meta["python_rng"]
            random.setstate((state[0], tuple(state[1]), state[2]))
            if hasattr(self.task, "restore_training_state") and "task" in meta:    # states before it resume without
                self.task.restore_training_state(parts.get("task", {}), meta["task"])
        return True

    def init_weights(self, path: str | Path, carry_step: bool = False) -> None:
        """Warm start from an exported model when there is no training state to resume. The
        exported model holds weights only (the EMA ones where there is an EMA), so the optimiser
        starts fresh and warms up over warmup_steps. By default this is step 0 of a new run (a
        fine-tune); carry_step continues the snapshot's step count instead, so the LR schedule,
        max_steps and the exported step keep counting steps of training in all."""
        if recover_checkpoint(self.out / STATE_DIR):
            return
        path = Path(path)
        meta = self.task.load_weights(self.model, path, continuing=carry_step) or {}
        if carry_step:
            step = int(meta.get("step", 0))
            if step >= self.optim_cfg.max_steps:
                raise ValueError(f"{path} was trained for {step} steps already; set --max-steps above {step} "
                                 "to train it further")
            self.step_count = self.warm_from = step
            self.samples_seen = int(meta.get("samples_seen", 0))
        if self.ema is not None:
            self.ema.load_state_dict(self.model.state_dict())

    @staticmethod
    def _forget_logged_steps_after(log_file: Path, step: int) -> None:
        """Drop log rows of steps past the resumed state (they were lost with the process and are
        run again), so the log has one row per step."""
        if not log_file.exists():
            return
        lines = [l for l in log_file.read_text(encoding="utf-8", errors="replace").splitlines() if l.strip()]
        keep = []
        for line in lines:
            try:
                if json.loads(line).get("step", 0) <= step:
                    keep.append(line)
            except (json.JSONDecodeError, AttributeError):      # a row torn by the kill
                pass
        if len(keep) != len(lines):
            atomic_write_text(log_file, "".join(l + "\n" for l in keep))

    # ------------------------------------------------------------ validation
    def _validation_due(self, total: int) -> bool:
        every = self.run_cfg.validate_every
        return (every > 0 and self.rank == 0 and hasattr(self.task, "validation_loss")
                and (self.step_count % every == 0 or self.step_count == total))

    def validate(self) -> float | None:
        """The loss of the model that gets exported (the EMA where there is one) on the task's
        held-out batches, without dropout, in fp32 whatever the run trains in: bf16 moved the wide
        teacher's loss by 0.0005, as much as 500 steps of training, so runs in either precision (and on
        CPUs with and without native bf16) would not compare."""
        model = self.ema or self.model
        was_training = model.training
        model.eval()
        try:
            with torch.no_grad():
                return self.task.validation_loss(model)
        finally:
            model.train(was_training)

    # ------------------------------------------------------------ the loop
    def fit(self) -> Path:
        resumed = self.try_resume()
        total = self.optim_cfg.max_steps
        log_file = self.out / "log.jsonl"
        if self.rank == 0:
            self.out.mkdir(parents=True, exist_ok=True)
            if resumed:
                tqdm.write(f"resumed {self.out} at step {self.step_count}", file=sys.stderr)
                self._forget_logged_steps_after(log_file, self.step_count)
        bar = tqdm(total=total, initial=self.step_count, disable=self.rank != 0, dynamic_ncols=True,
                   desc=self.task.kind)
        t0, n0 = time.time(), 0
        window: dict[str, list[float]] = {}
        while self.step_count < total:
            batch = self.task.batch(self.rng)
            logs = self.step(batch)
            for k, v in logs.items():
                window.setdefault(k, []).append(v)
            n = self.optim_cfg.batch_size * self.world
            self.samples_seen += n
            n0 += n
            bar.update(1)
            validate = self._validation_due(total)
            if self.step_count % self.run_cfg.log_every == 0 or self.step_count == total or validate:
                rate = n0 / max(time.time() - t0, 1e-9)
                # one step's loss and batch statistics are mostly its draw: the log keeps the means since the
                # last line (over the steps that reported each), and the learning rate as it is now
                logs = {k: sum(v) / len(v) for k, v in window.items()} | {"lr": logs["lr"]}
                window = {}
                val = self.validate() if validate else None
                if val is not None:
                    logs["val_loss"] = val
                    tqdm.write(f"step {self.step_count}: validation loss {val:.5f}", file=sys.stderr)
                t0, n0 = time.time(), 0
                bar.set_postfix(loss=f"{logs['loss']:.4f}", samples_s=f"{rate:.1f}")
                if self.rank == 0:
                    with open(log_file, "a") as f:
                        f.write(json.dumps({"step": self.step_count, "samples_per_s": round(rate, 2),
                                            "time": time.time(), **logs}) + "\n")
            if self.step_count % self.run_cfg.checkpoint_every == 0 or self.step_count == total:
                started = time.time()
                # the export first: a process killed while exporting (or judging the export) resumes from the
                # checkpoint before and exports this step again, rather than going on with it never exported
                if self.rank == 0:
                    self.task.export(self.ema or self.model, self.out / "model",
                                     {"step": self.step_count, "samples_seen": self.samples_seen})
                self.save_state()
                # samples/s is the training's: a judged export takes minutes, which would read as slow steps
                t0 += time.time() - started
        bar.close()
        if dist.is_initialized():
            dist.barrier()
        return self.out / "model"
