"""A teacher training step (batch 32, 30 latent frames, bf16 autocast) and one CFG forward (2 rows, fp32).

    train_step.py [--adamw default|fused|foreach] [--clip]

--adamw picks torch's AdamW implementation (default: its CPU default, the per-parameter loop); --clip clips the
gradient norm as the trainer does. runs.log's rows ran without either option; the optimiser table with --clip.
"""
import argparse
import time

import torch

torch.set_num_threads(2)
from salad.bench import PROMPT, _load  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--adamw", choices=("default", "fused", "foreach"), default="default")
ap.add_argument("--clip", action="store_true")
args = ap.parse_args()
pipe = _load("embedded", False)
den = pipe.denoiser.train().requires_grad_(True)
torch.manual_seed(0)
B, T = 32, 30
z, t = torch.randn(B, T, 7, 32), torch.randint(0, 1000, (B,))
text = torch.randn(B, 11, den.config.text_dim)
impl = {"fused": {"fused": True}, "foreach": {"foreach": True}}.get(args.adamw, {})
opt = torch.optim.AdamW(den.parameters(), 1e-5, **impl)


def step():
    with torch.autocast("cpu", torch.bfloat16):
        loss = den(z, t, text).float().pow(2).mean()
    opt.zero_grad(set_to_none=True)
    loss.backward()
    if args.clip:
        torch.nn.utils.clip_grad_norm_(den.parameters(), 1.0)
    opt.step()


def best(f, n):
    ts = []
    for _ in range(n):
        t0 = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t0)
    return round(1000 * min(ts), 2), round(1000 * sorted(ts)[n // 2], 2)


for _ in range(3):
    step()
print(args.adamw, "train step ms", best(step, 10))
print(args.adamw, "opt.step ms", best(opt.step, 20))
den.eval()
cond = pipe.sampler_text([PROMPT], "ddim")
fn = pipe.model_fn(cond, auto=False)
x = torch.randn(cond.tokens.shape[0], 30, 7, 32)
tt = torch.full((x.shape[0],), 500)
with torch.no_grad():
    for _ in range(3):
        fn(x, tt)
    print("teacher cfg fwd ms", best(lambda: fn(x, tt), 20))
