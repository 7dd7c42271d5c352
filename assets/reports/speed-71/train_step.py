"""A teacher training step (batch 32, 30 latent frames, bf16 autocast, AdamW) and one CFG forward (2 rows, fp32)."""
import time

import torch

torch.set_num_threads(2)
from salad.bench import PROMPT, _load  # noqa: E402

pipe = _load("embedded", False)
den = pipe.denoiser.train().requires_grad_(True)
torch.manual_seed(0)
B, T = 32, 30
z, t = torch.randn(B, T, 7, 32), torch.randint(0, 1000, (B,))
text = torch.randn(B, 11, den.config.text_dim)
opt = torch.optim.AdamW(den.parameters(), 1e-5)


def step():
    with torch.autocast("cpu", torch.bfloat16):
        loss = den(z, t, text).float().pow(2).mean()
    loss.backward()
    opt.step()
    opt.zero_grad()


for _ in range(3):
    step()
ts = []
for _ in range(8):
    t0 = time.perf_counter()
    step()
    ts.append(time.perf_counter() - t0)
print("train step ms", round(1000 * min(ts), 1), round(1000 * sorted(ts)[4], 1))
den.eval()
cond = pipe.sampler_text([PROMPT], "ddim")
fn = pipe.model_fn(cond, auto=False)
x = torch.randn(cond.tokens.shape[0], 30, 7, 32)
tt = torch.full((x.shape[0],), 500)
with torch.no_grad():
    for _ in range(3):
        fn(x, tt)
    ts = []
    for _ in range(20):
        t0 = time.perf_counter()
        fn(x, tt)
        ts.append(time.perf_counter() - t0)
print("teacher cfg fwd ms", round(1000 * min(ts), 2), round(1000 * sorted(ts)[10], 2))
