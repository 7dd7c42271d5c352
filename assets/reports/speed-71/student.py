"""One student forward (the 4-step sampler's unit) and `salad bench`'s 4-step generation, fp32, batch 1, 6 s."""
import time

import torch

torch.set_num_threads(2)
from salad.bench import PROMPT, _load  # noqa: E402

pipe = _load("embedded", False)
text = pipe.sampler_text([PROMPT], "consistency")
fn = pipe.student_fn(text, False, 7.5)
torch.manual_seed(0)
x = torch.randn(1, pipe.frames_for(6.0) // 4, 7, pipe.student.config.latent_dim)
t = torch.full((1,), 500)


def best(f, n):
    ts = []
    for r in range(n):
        t0 = time.perf_counter()
        f(r)
        ts.append(time.perf_counter() - t0)
    return round(1000 * min(ts), 2), round(1000 * sorted(ts)[len(ts) // 2], 2)


with torch.no_grad():
    for _ in range(5):
        fn(x, t)
    print("fwd", best(lambda r: fn(x, t), 40))
pipe.generate(PROMPT, seconds=6.0, steps=2, sampler="consistency")
print("gen", best(lambda r: pipe.generate(PROMPT, seed=r, seconds=6.0, steps=4, sampler="consistency"), 12))
