"""Several linear maps of one input, applied as one product.

At batch 1 a denoiser's projections are small enough that each call costs about as much in
dispatch as in arithmetic; stacking the weights of maps that read the same input (a layer's
query, key and value; every FiLM's scale and shift) saves the extra calls. The modules keep their
own parameters, so checkpoints are unchanged.
"""
from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F


class StackedLinears(nn.Module):
    """Called with an input and the nn.Linear modules to stack, gives their outputs concatenated
    along the last dimension (the modules are passed on every call, not held, so a copied model
    never reads its original's weights). Outside autograd and compilation the stacked weights are
    kept, as buffers that go wherever the model goes and are never saved, until one of the
    parameters is replaced or changed in place (an optimiser step or load_state_dict bumps its
    version); while autograd records, they are stacked anew so gradients reach every module."""

    def __init__(self):
        super().__init__()
        self.register_buffer("stacked_weight", None, persistent=False)
        self.register_buffer("stacked_bias", None, persistent=False)
        self._key: tuple | None = None

    def weights(self, linears: list[nn.Linear]) -> tuple[torch.Tensor, torch.Tensor]:
        params = [p for lin in linears for p in (lin.weight, lin.bias)]
        if torch.compiler.is_compiling() or (torch.is_grad_enabled() and any(p.requires_grad for p in params)):
            return torch.cat([lin.weight for lin in linears]), torch.cat([lin.bias for lin in linears])
        key = tuple((p.data_ptr(), p._version) for p in params)
        if self.stacked_weight is None or self._key != key:
            with torch.inference_mode(False):   # a stack built under inference_mode could not join a later graph
                self.stacked_weight = torch.cat([lin.weight for lin in linears]).detach()
                self.stacked_bias = torch.cat([lin.bias for lin in linears]).detach()
            self._key = key
        return self.stacked_weight, self.stacked_bias

    def forward(self, x: torch.Tensor, linears: list[nn.Linear]) -> torch.Tensor:
        return F.linear(x, *self.weights(linears))
