"""How long a motion a caption asks for: a small regressor over the caption index's text features.

The length prior took the median length of the motions of a prompt's 8 nearest training captions. Text
neighbours share wording more than duration (the nearest captions of "a man shows someone where to go with
his right hand" are pointing gestures, 2.2 s against guiding's 5 s), and a regressor fitted to every training
caption generalises further. Every caption of the Bandai validation and test splits against its own motion's
length, within +-35%: 0.94 and 0.96 of them with the net, 0.90 and 0.90 with the neighbours. It is an ensemble
of MEMBERS small MLPs, each fitted to log seconds with an L1 loss (a median, as the neighbours gave) from its
own seed, their log predictions averaged (single members scored 0.933-0.944 on validation; four average out
the seed); width and epochs were chosen on the validation split.
"""
from __future__ import annotations

import math

import torch
from torch import nn

MEMBERS = 4
HIDDEN = 512
EPOCHS = 40
# a small caption set gets more passes, so that it is fitted too
MIN_STEPS = 300
BATCH = 256
LR = 1e-3
WEIGHT_DECAY = 1e-4
PREFIX = "length_net"


def _member(dim: int, hidden: int) -> nn.Sequential:
    return nn.Sequential(nn.Linear(dim, hidden), nn.GELU(), nn.Linear(hidden, hidden), nn.GELU(), nn.Linear(hidden, 1))


class LengthNet:
    """Caption-index points (n, dim) -> seconds (n,)."""

    def __init__(self, members: list[nn.Sequential]):
        self.members = [m.eval() for m in members]

    @classmethod
    def fit(cls, points: torch.Tensor, seconds: torch.Tensor, members: int = MEMBERS, hidden: int = HIDDEN,
            epochs: int = EPOCHS, seed: int = 0) -> "LengthNet":
        """Fitted to `seconds` of `points`; the same inputs and seed give the same weights on one machine."""
        x, y = points.float(), seconds.float().log()
        epochs = max(epochs, math.ceil(MIN_STEPS / math.ceil(len(x) / BATCH)))
        fitted = []
        for i in range(members):
            g = torch.Generator().manual_seed(seed + i)
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(seed + i)
                net = _member(x.shape[1], hidden)
            opt = torch.optim.AdamW(net.parameters(), lr=LR, weight_decay=WEIGHT_DECAY)
            for _ in range(epochs):
                for batch in torch.randperm(len(x), generator=g).split(BATCH):
                    loss = (net(x[batch])[:, 0] - y[batch]).abs().mean()
                    opt.zero_grad(set_to_none=True)
                    loss.backward()
                    opt.step()
            fitted.append(net)
        return cls(fitted)

    @torch.no_grad()
    def __call__(self, points: torch.Tensor) -> torch.Tensor:
        x = points.float()
        return torch.stack([m(x)[:, 0] for m in self.members]).mean(0).exp()

    def tensors(self) -> dict[str, torch.Tensor]:
        return {f"{PREFIX}.{i}.{k}": v.contiguous() for i, m in enumerate(self.members)
                for k, v in m.state_dict().items()}

    @classmethod
    def from_tensors(cls, t: dict[str, torch.Tensor], dim: int) -> "LengthNet | None":
        """The net in `t` (tensors read from vocabulary.safetensors), or None where there is none or it does not
        take points of `dim` components."""
        members = []
        while f"{PREFIX}.{len(members)}.0.weight" in t:
            i = len(members)
            state = {k[len(f"{PREFIX}.{i}."):]: v.float() for k, v in t.items() if k.startswith(f"{PREFIX}.{i}.")}
            first = state["0.weight"]
            if first.ndim != 2 or first.shape[1] != dim:
                return None
            net = _member(dim, first.shape[0])
            try:
                net.load_state_dict(state)
            except RuntimeError:
                return None
            if not all(torch.isfinite(p).all() for p in net.parameters()):
                return None
            members.append(net)
        return cls(members) if members else None
