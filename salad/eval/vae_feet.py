"""What a VAE's decoder does to the feet: `salad eval-vae`.

Every test motion goes through each VAE (posterior mean, and one posterior sample as the
denoiser's training latents are drawn), and the reconstruction is measured where animators look:

* pose error: mean joint distance (root-aligned, metres) to the real motion;
* still-foot share on walking clips (a toe standing still, physics.still_foot_share): real
  walking keeps one foot planted almost always, so this drops where a decoder makes feet slide;
* contact-slide share on locomotion clips (a touching toe sliding, physics.contact_slide_share);
* speed ratio on locomotion clips: the reconstruction's mean horizontal root speed over the real
  one's (a decoder can plant the feet by slowing the whole walk down).

    salad eval-vae --data data/bandai-hml --vae assets/model/vae [--vae OTHER ...] --out DIR
"""
from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from ..data.dataset import MotionDataset
from ..data.labels import read_labels
from ..files import atomic_write_text
from ..models.io import load_vae
from ..motion import representation as rep
from .physics import contact_slide_share, still_foot_share

LOCOMOTION = ("walk", "run", "dash")          # content labels that start with one of these


def _is_walk(content: str) -> bool:
    return content.startswith("walk")


def _is_locomotion(content: str) -> bool:
    return content.startswith(LOCOMOTION)


def _root_speed(joints: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(joints[:, 0, [0, 2]], axis=0), axis=-1).mean() * rep.FPS)


def _reconstruct(vae, norm, features: np.ndarray, sample: bool, generator: torch.Generator,
                 device: torch.device) -> tuple[np.ndarray, np.ndarray | None]:
    """Joints decoded from the posterior mean, and (with `sample`) from one posterior sample."""
    x = torch.from_numpy(norm.normalize(features)).float()[None].to(device)
    joints = lambda z: rep.features_to_joints(norm.denormalize(vae.decode(z)[0][0].double().cpu().numpy()))
    with torch.no_grad():
        mu, logvar = vae.encode(x)
        if not sample:
            return joints(mu), None
        # the noise is drawn on the CPU, so a seed gives the same draw on any device
        eps = torch.randn(mu.shape, generator=generator).to(device)
        return joints(mu), joints(mu + eps * torch.exp(0.5 * logvar))


def evaluate_vae(vae_dir: str | Path, data_root: str | Path, split: str = "test", seed: int = 0,
                 max_frames: int = 196, progress: Callable[[int, int], None] | None = None,
                 device: str | torch.device = "cpu") -> dict[str, Any]:
    device = torch.device(device)
    vae, norm, _, _ = load_vae(vae_dir)
    vae.eval().to(device)
    labels = read_labels(data_root)
    ds = MotionDataset(data_root, split, min_frames=16, max_frames=max_frames, normalizer=norm)
    g = torch.Generator().manual_seed(seed)
    rows: dict[str, list[float]] = {k: [] for k in ("pose_error_m", "walk_still_real", "walk_still_mean",
                                                     "walk_still_sample", "slide_real", "slide_mean",
                                                     "speed_ratio")}
    t0 = time.time()
    for i, it in enumerate(ds.items):
        f = it.features[: len(it.features) // 4 * 4].astype(np.float64)
        real = rep.features_to_joints(f)
        lab = labels.get(it.name.split("@")[0])
        walk = lab is not None and _is_walk(lab.content)
        mean, sampled = _reconstruct(vae, norm, f, walk, g, device)
        rows["pose_error_m"].append(float(np.linalg.norm((mean - mean[:, :1]) - (real - real[:, :1]), axis=-1).mean()))
        if walk:
            rows["walk_still_real"].append(still_foot_share(real))
            rows["walk_still_mean"].append(still_foot_share(mean))
            rows["walk_still_sample"].append(still_foot_share(sampled))
        if lab is not None and _is_locomotion(lab.content):
            rows["slide_real"].append(contact_slide_share(real))
            rows["slide_mean"].append(contact_slide_share(mean))
            rows["speed_ratio"].append(_root_speed(mean) / max(_root_speed(real), 1e-6))
        if progress:
            progress(i + 1, len(ds.items))
    if not rows["walk_still_real"]:
        raise ValueError(f"{data_root}: no walking clips in the {split} split (labels.json content 'walk...')")
    return {"vae": str(vae_dir), "clips": len(ds.items), "walking_clips": len(rows["walk_still_real"]),
            "locomotion_clips": len(rows["slide_real"]), "seconds": round(time.time() - t0, 1),
            **{k: float(np.mean(v)) for k, v in rows.items()}}


def report_markdown(results: list[dict[str, Any]], split: str) -> str:
    lines = [f"# VAE reconstruction and the feet ({split} split)", "",
             "Pose error: mean root-aligned joint distance of the posterior-mean reconstruction. Still-foot share: "
             "frames with a toe under 0.2 m/s, on walking clips. Contact slide: frames where a touching toe slides "
             "faster than 0.5 m/s, on walk / run / dash clips. Speed: mean root speed of the reconstruction over "
             "the real one's, on the same clips. 'sample' decodes one posterior sample, as the denoiser's training "
             "latents are drawn.", "",
             "| VAE | pose error (cm) | still feet: real / mean / sample | contact slide: real / mean | speed |",
             "|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| `{r['vae']}` | {100 * r['pose_error_m']:.2f} | {r['walk_still_real']:.3f} / "
                     f"{r['walk_still_mean']:.3f} / {r['walk_still_sample']:.3f} | {r['slide_real']:.3f} / "
                     f"{r['slide_mean']:.3f} | {r['speed_ratio']:.3f} |")
    r = results[0]
    lines += ["", f"{r['clips']} clips, of which {r['walking_clips']} walking and {r['locomotion_clips']} locomotion."]
    return "\n".join(lines) + "\n"


def write_vae_report(results: list[dict[str, Any]], out_dir: str | Path, split: str) -> Path:
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps({"split": split, "rows": results}, indent=2))
    path = out / "report.md"
    atomic_write_text(path, report_markdown(results, split))
    return path
