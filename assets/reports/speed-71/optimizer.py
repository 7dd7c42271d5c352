"""A teacher training step (batch 32, bf16 autocast, gradient clipping) with AdamW as given: default | fused | foreach."""
import sys
import time

import torch

torch.set_num_threads(2)
from salad.bench import _load  # noqa: E402

pipe = _load("embedded", False)
den = pipe.denoiser.train().requires_grad_(True)
torch.manual_seed(0)
B, T = 32, 30
z, t = torch.randn(B, T, 7, 32), torch.randint(0, 1000, (B,))
text = torch.randn(B, 11, den.config.text_dim)
mode = sys.argv[1]
kw = {"fused": True} if mode == "fused" else {"foreach": True} if mode == "foreach" else {}
opt = torch.optim.AdamW(den.parameters(), 1e-5, **kw)


def step():
    with torch.autocast("cpu", torch.bfloat16):
        loss = den(z, t, text).float().pow(2).mean()
    opt.zero_grad(set_to_none=True)
    loss.backward()
    torch.nn.utils.clip_grad_norm_(den.parameters(), 1.0)
    opt.step()


for _ in range(3):
    step()
ts = []
for _ in range(10):
    t0 = time.perf_counter()
    step()
    ts.append(time.perf_counter() - t0)
print(mode, "train step ms", round(1000 * min(ts), 1), round(1000 * sorted(ts)[5], 1))
t0 = time.perf_counter()
for _ in range(20):
    opt.step()
print(mode, "opt.step ms", round((time.perf_counter() - t0) / 20 * 1000, 2))
