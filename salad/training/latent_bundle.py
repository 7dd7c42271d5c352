"""Denoiser training data without the motion dataset or the text encoder: the frozen VAE's
posterior means and the captions' token features, split into parts of bounded size.

A GPU lent for minutes is reached by transfers of at most 64 MiB. The Bandai build's
features are 0.4 GB; its training motions' latents are ~58 MB in fp16 and their captions'
token features ~140 MB (bf16 tokens, fp32 sentence features), so the bundle goes over in
parts, each with the checksum that load_checkpoint verifies. Latents are stored per motion
only as far as they differ from those of an empty canvas (the encoder sees ~3 latent frames
past a motion's end; beyond that every motion's padding encodes alike), and a motion longer
than the canvas as a few windows at evenly spaced offsets instead of a fresh random window
per draw.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from ..checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from ..data.labels import content_of
from ..models.text import tower_token_features
from ..models.text_bank import TextBank

KIND = "latent-bundle"
TEXT_CHUNK_ROWS = 16384          # token rows per stored tensor, so the text spreads over parts
HEADER_BYTES = 256               # a tensor's share of its file's safetensors header, at most
TEXT_FORMS = ("features", "tower")


@torch.no_grad()
def write_bundle(task, out: str | Path, part_bytes: int, windows: int = 8, progress: bool = True,
                 text: str = "features") -> Path:
    """Write the training data of `task` (a DenoiserTask over a dataset) as a bundle at `out`.

    text="features" stores every caption's token features (task.text); "tower" stores the captions'
    token ids and the text encoder's weights cut to them instead, and the features are computed where
    the bundle is read: ~21 MB rather than ~10 KB a caption, which makes a many-caption build fit a
    bounded transfer (the 12-caption Bandai build's features are 417 MiB)."""
    from tqdm import tqdm

    if part_bytes <= HEADER_BYTES:
        raise ValueError(f"parts must hold more than {HEADER_BYTES} bytes, got {part_bytes}")
    if windows < 1:
        raise ValueError(f"windows must be >= 1, got {windows}")
    if text not in TEXT_FORMS:
        raise ValueError(f"text must be one of {', '.join(TEXT_FORMS)}, got {text!r}")
    if text == "tower" and not hasattr(task.text_encoder, "trimmed_tower"):
        raise ValueError(f"the {task.text_spec.get('name')} text encoder cannot be stored as a cut tower; "
                         "write this bundle with its token features (text='features')")
    items = task.dataset.items
    canvas = task.canvas
    try:
        content = content_of(task.dataset.root, [it.name for it in items])
    except (FileNotFoundError, ValueError):      # unlabelled data: a bundle that trains with data.balance = 1 only
        content = None

    empty = task.encode([np.zeros((0, task.dataset.dim), np.float32)])[0][0]
    tensors: dict[str, torch.Tensor] = {"empty": empty}
    fits = [i for i, it in enumerate(items) if len(it.features) <= canvas]
    for s in tqdm(range(0, len(fits), 64), desc="latents", disable=not progress):
        ids = fits[s:s + 64]
        mu, _ = task.encode([items[i].features[: len(items[i].features) // 4 * 4] for i in ids])
        for k, i in enumerate(ids):
            differs = torch.nonzero((mu[k] - empty).abs().flatten(1).amax(1) > 1e-6).flatten()
            keep = int(differs.max()) + 1 if len(differs) else 0
            tensors[f"prefix.{i}"] = mu[k, :keep].to(torch.float16)
    for i, it in enumerate(items):
        if len(it.features) > canvas:
            starts = np.round(np.linspace(0, len(it.features) - canvas, windows)).astype(int)
            tensors[f"windows.{i}"] = task.encode([it.features[s:s + canvas] for s in starts])[0].to(torch.float16)
    tower_config = None
    if text == "tower":
        captions = TextBank.distinct([c for cs in task.captions for c in cs])
        ids, lengths, state, tower_config = task.text_encoder.trimmed_tower(captions)
        tensors["text.ids"], tensors["text.lengths"] = ids, lengths
        tensors.update({f"tower.{k}": v for k, v in state.items()})
    else:
        captions = task.text.captions
        flat, lengths, pooled = task.text.tensors()
        for name, rows_of in (("flat", flat), ("pooled", pooled)):
            per_row = rows_of.shape[1] * rows_of.element_size()
            rows = max(1, min(TEXT_CHUNK_ROWS, (part_bytes - HEADER_BYTES) // per_row))
            for j, s in enumerate(range(0, len(rows_of), rows)):
                tensors[f"text.{name}.{j}"] = rows_of[s:s + rows]
        tensors["text.lengths"] = lengths

    parts: dict[str, dict[str, torch.Tensor]] = {}
    size = part_bytes
    for name, t in tensors.items():
        n = t.numel() * t.element_size() + HEADER_BYTES
        if n > part_bytes:
            raise ValueError(f"{name} alone is {n:,} bytes, more than a part may hold ({part_bytes:,})")
        if size + n > part_bytes:
            parts[f"part-{len(parts)}"] = {}
            size = 0
        parts[f"part-{len(parts) - 1}"][name] = t.contiguous()
        size += n
    config = {"canvas": canvas, "latent_scale": task.latent_scale, "vae_checksum": task.vae_checksum,
              "text_encoder": task.text_spec, "text_captions": captions, "text_tower": tower_config,
              "lengths": [len(it.features) for it in items], "captions": [list(it.captions) for it in items],
              "content": content, "windows": windows}
    return save_checkpoint(out, KIND, config, parts, {"motions": len(items), "source": str(task.cfg.data.root)})


class LatentBundle:
    """A bundle read back: per-motion lengths, captions and content classes, the posterior means
    on the canvas, and the text bank."""

    def __init__(self, path: str | Path, device: torch.device | str = "cpu"):
        """`device` computes the text features of a bundle that stores the cut text tower."""
        doc, parts = load_checkpoint(path, kind=KIND)
        c = doc["config"]
        t: dict[str, torch.Tensor] = {}
        for p in parts.values():
            t.update(p)
        self.path = Path(path)
        self.canvas, self.latent_scale = int(c["canvas"]), float(c["latent_scale"])
        self.vae_checksum, self.text_spec = c["vae_checksum"], c["text_encoder"]
        self.lengths = np.asarray(c["lengths"], dtype=np.int64)
        self.captions: list[list[str]] = c["captions"]
        self.content: list[str] | None = c["content"]
        empty = t["empty"].float()
        n = len(self.lengths)
        self.means = empty.expand(n, *empty.shape).clone()
        self.window_of = np.full(n, -1)
        wins = []
        for i in range(n):
            if f"prefix.{i}" in t:
                p = t[f"prefix.{i}"].float()
                self.means[i, :len(p)] = p
            elif f"windows.{i}" in t:
                self.window_of[i] = len(wins)
                wins.append(t[f"windows.{i}"].float())
            else:
                raise CheckpointError(f"{path}: no latents for motion {i}")
        self.windows = torch.stack(wins) if wins else torch.zeros(0, int(c["windows"]), *empty.shape)
        if "text.ids" in t:
            state = {k[len("tower."):]: v for k, v in t.items() if k.startswith("tower.")}
            flat, pooled = tower_token_features(t["text.ids"], t["text.lengths"], state, c["text_tower"], device)
            self.text = TextBank.from_tensors(c["text_captions"], flat.to(torch.bfloat16), t["text.lengths"], pooled)
            return
        def joined(name: str) -> torch.Tensor:
            if f"text.{name}" in t:      # bundles written before the pooled features were chunked
                return t[f"text.{name}"]
            chunks = sorted((k for k in t if k.startswith(f"text.{name}.")), key=lambda k: int(k.rsplit(".", 1)[1]))
            return torch.cat([t[k] for k in chunks])
        self.text = TextBank.from_tensors(c["text_captions"], joined("flat"), t["text.lengths"], joined("pooled"))

    def rows(self, idx: Sequence[int], rng: np.random.Generator) -> torch.Tensor:
        """Posterior means on the canvas of motions `idx`; a motion longer than the canvas gives one
        of its windows, drawn at random."""
        out = self.means[torch.as_tensor(np.asarray(idx), dtype=torch.long)]
        for b, i in enumerate(idx):
            if self.window_of[i] >= 0:
                out[b] = self.windows[self.window_of[i], int(rng.integers(self.windows.shape[1]))]
        return out
