"""Denoised latents: what the decoder is given in use, paired with the real motion it should show.

Generated feet slide although real motion decoded from its own latents keeps them planted: the
denoisers' latents carry errors the decoder never saw in training (posterior samples of real
motion). Here each training clip's latent mean is noised part of the way and denoised again under
one of its captions, by the teacher (DDIM with the pipeline's sampling settings) or by the
distilled student, and the result is stored beside the clip it came from. The decoder fine-tune
(training/vae_adv_task.py, `denoised_latents`) decodes those latents and is held to the real clip,
so it learns to undo the denoisers' errors; the encoder and latent space stay as they are.

The file is safetensors: `latents` (sum of the clips' latent frames, parts, D), unscaled (the
VAE's own units), with `offsets` (N + 1) into it; metadata holds the clip names (each latent covers
its clip from the first frame), the sampler and starting timestep of each, and the latent space's checksum.
"""
from __future__ import annotations

import json
import os
from itertools import groupby
from pathlib import Path

import numpy as np
import torch
from safetensors import safe_open
from safetensors.torch import save_file
from tqdm import tqdm

from ..data.dataset import MotionDataset
from ..models.io import vae_latent_origin

FORMAT = "salad-denoised-latents-1"
MIN_FRAMES = 64          # the decoder fine-tune's window (configs/vae_denoised.toml): shorter clips give none
TEACHER_LEVELS = (0.15, 0.5)   # noise levels (share of T) the teacher starts from, drawn uniformly
STUDENT_STARTS = (2, 3)        # the 4-step student starts at its 3rd or 4th step (t = 499 or 259)


def _start_step(timesteps, level: float) -> int:
    """The first solver step whose timestep lies below `level` (a timestep)."""
    return next((i for i, t in enumerate(timesteps) if int(t) < level), len(timesteps) - 1)


@torch.no_grad()
def build_denoised_latents(pipe, dataset: MotionDataset, out: str | os.PathLike, model_dir: str | os.PathLike,
                           seed: int = 0, batch: int = 32, student_share: float = 0.5, cfg: float = 7.5,
                           min_frames: int = MIN_FRAMES, show_progress: bool = True) -> Path:
    """One denoised latent for each clip of `dataset` (its first pipe.canvas_frames) of at least
    min_frames frames, denoised by the student with probability student_share, else by the
    teacher. Written atomically to `out`."""
    if not 0 <= student_share <= 1:
        raise ValueError(f"student_share must be in [0, 1], got {student_share}")
    if student_share > 0 and pipe.student is None:
        raise ValueError(f"{model_dir} has no consistency student: give student_share 0")
    rng = np.random.default_rng(seed)
    canvas = pipe.canvas_frames
    clips = [(i, min(len(it.features), canvas) // 4 * 4) for i, it in enumerate(dataset.items)]
    clips = [(i, n) for i, n in clips if n >= min_frames]
    if not clips:
        raise ValueError(f"no clip of {dataset.root} has {min_frames} frames or more")
    teacher_steps = [int(t) for t in pipe.schedule.sampler("ddim", 50).timesteps]
    jobs = []
    for i, n in clips:
        student = bool(rng.random() < student_share)
        level = float(rng.uniform(*TEACHER_LEVELS)) * pipe.schedule.config.train_steps
        jobs.append(dict(item=i, frames=n, caption=str(rng.choice(dataset.items[i].captions)), student=student,
                         start=int(rng.choice(STUDENT_STARTS)) if student else _start_step(teacher_steps, level)))
    # a batch shares its sampler and first step; sorted by length within, so little of it is padding
    order = sorted(range(len(jobs)), key=lambda j: (jobs[j]["student"], jobs[j]["start"], jobs[j]["frames"]))
    latents: dict[int, torch.Tensor] = {}
    bar = tqdm(total=len(jobs), desc="denoised latents", disable=not show_progress)
    k = 0
    for _, same in groupby(order, key=lambda j: (jobs[j]["student"], jobs[j]["start"])):
        same = list(same)
        for c in range(0, len(same), batch):
            group = same[c:c + batch]
            for j, z in zip(group, _denoise_group(pipe, dataset, [jobs[j] for j in group], seed + k, cfg)):
                latents[j] = z
            bar.update(len(group))
            k += len(group)
    bar.close()
    zs = [latents[j] for j in range(len(jobs))]
    offsets = np.cumsum([0] + [z.shape[0] for z in zs])
    meta = {
        "format": FORMAT,
        "latent_origin_sha256": vae_latent_origin(Path(model_dir) / "vae"),
        "model": str(model_dir),
        "data": str(dataset.root),
        "names": json.dumps([dataset.items[j["item"]].name for j in jobs]),
        "samplers": json.dumps(["consistency" if j["student"] else "ddim" for j in jobs]),
        "timesteps": json.dumps([j["timestep"] for j in jobs]),
        "seed": str(seed),
    }
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".tmp")
    save_file({"latents": torch.cat(zs).contiguous(), "offsets": torch.from_numpy(offsets.astype(np.int64))},
              str(tmp), metadata=meta)
    os.replace(tmp, out)
    return out


def _denoise_group(pipe, dataset: MotionDataset, jobs: list[dict], seed: int, cfg: float) -> list[torch.Tensor]:
    """Noise each job's clip latent to its level and denoise it with one sampler in one batch;
    returns the latents unscaled, each (frames/4, parts, D). Sets job["timestep"]; every job
    shares its sampler and start step."""
    student = jobs[0]["student"]
    sampler, steps = ("consistency", 4) if student else ("ddim", 50)
    T = max(j["frames"] for j in jobs)
    B = len(jobs)
    mask = torch.arange(T // 4)[None] < torch.tensor([j["frames"] for j in jobs])[:, None] // 4
    # each clip encoded alone, as the denoiser's training latents were: no padding in the encoder's view
    c = pipe.denoiser.config
    z0 = torch.zeros(B, T // 4, c.parts, c.latent_dim)
    for b, j in enumerate(jobs):
        x = dataset.normalizer.normalize(dataset.items[j["item"]].features[:j["frames"]])
        mu, _ = pipe.vae.encode(torch.from_numpy(x).float()[None].to(pipe.device))
        z0[b, :j["frames"] // 4] = mu[0].float().cpu() * pipe.latent_scale
    timesteps = [int(t) for t in pipe.schedule.sampler(sampler, steps).timesteps]
    start = jobs[0]["start"]
    t = torch.full((B,), timesteps[start], dtype=torch.long)
    noisy = pipe.schedule.add_noise(z0, pipe.noise(B, T, seed).cpu(), t) * mask[:, :, None, None]
    text = pipe.sampler_text([j["caption"] for j in jobs], sampler)
    z = pipe.denoise(text, noisy.to(pipe.device), sampler, steps, cfg, auto=False, seed=seed,
                     frame_mask=mask.to(pipe.device), start=start)
    out = []
    for b, j in enumerate(jobs):
        j["timestep"] = timesteps[start]
        out.append((z[b, :j["frames"] // 4].float().cpu() / pipe.latent_scale).contiguous())
    return out


class DenoisedLatents:
    """A denoised-latents file, read whole: latent(k) is clip k's, names[k] its dataset item."""

    def __init__(self, path: str | os.PathLike):
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such denoised-latents file (salad data denoised-latents)")
        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            if meta.get("format") != FORMAT:
                raise ValueError(f"{path}: not a denoised-latents file (format {meta.get('format')!r})")
            self.latents, self.offsets = f.get_tensor("latents"), f.get_tensor("offsets")
        self.path = path
        self.names: list[str] = json.loads(meta["names"])
        self.samplers: list[str] = json.loads(meta["samplers"])
        self.latent_origin = meta["latent_origin_sha256"]
        if len(self.offsets) != len(self.names) + 1 or int(self.offsets[-1]) != len(self.latents):
            raise ValueError(f"{path}: offsets do not match the latents")

    def __len__(self) -> int:
        return len(self.names)

    def latent(self, k: int) -> torch.Tensor:
        return self.latents[int(self.offsets[k]):int(self.offsets[k + 1])]
