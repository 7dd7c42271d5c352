"""Skeleto-temporal VAE (SALAD §3.1, supp. A.1), with MoLA's activation channel.

Motion features are split per joint, lifted by joint-wise MLPs to (T, 22, D), mixed by
skeleto-temporal convolutions, and pooled 22 -> 12 -> 7 joints and T -> T/4 frames into
a latent of shape (T/4, 7, D). The decoder mirrors this. An optional per-frame
activation channel (1 = motion, 0 = padding after the end) rides on the root joint, so
the decoder can say where a generated motion ends.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..motion import representation as rep
from ..motion import skeleton as sk


@dataclass
class VAEConfig:
    latent_dim: int = 32
    kernel_size: int = 3
    blocks_per_level: int = 2
    dropout: float = 0.1
    activation_channel: bool = True   # MoLA's per-frame "is the motion still going" flag
    # the decoder's channel width (0: latent_dim, the paper's symmetric VAE); a wider one decodes the
    # same latents, its extra channels starting at zero (widen_decoder)
    decoder_dim: int = 0
    lambda_pos: float = 0.5
    lambda_vel: float = 0.5
    lambda_kl: float = 0.02
    lambda_act: float = 1.0


def _joint_dims(activation_channel: bool) -> list[int]:
    dims = [len(i) for i in rep.joint_feature_indices()]
    if activation_channel:
        dims[0] += 1
    return dims


class JointwiseMLP(nn.Module):
    """One small MLP per joint: the joints carry different features (7, 12 or 13 dims)."""

    def __init__(self, in_dims: list[int], out_dims: list[int], hidden: int):
        super().__init__()
        self.nets = nn.ModuleList(
            nn.Sequential(nn.Linear(i, hidden), nn.GELU(), nn.Linear(hidden, o))
            for i, o in zip(in_dims, out_dims))

    def forward(self, parts: list[torch.Tensor]) -> list[torch.Tensor]:
        return [net(p) for net, p in zip(self.nets, parts)]


class STConv(nn.Module):
    """SkelConv (graph convolution over neighbouring joints) + TempConv (1-D over frames).

    Tensors are laid out (B, D, J, T) so both parts run as 2-D convolutions without
    permuting memory: the temporal kernel is (1, k), and the skeletal part is a fixed
    neighbour-averaging matmul over J followed by a 1x1 convolution.
    """

    def __init__(self, level: sk.SkeletonLevel, dim: int, kernel_size: int):
        super().__init__()
        adj = torch.from_numpy(level.adjacency())
        self.register_buffer("neighbour_mean", adj / adj.sum(1, keepdim=True), persistent=False)
        self.self_proj = nn.Linear(dim, dim)
        self.neighbour_proj = nn.Linear(dim, dim)
        self.temporal = nn.Conv1d(dim, dim, kernel_size, padding=kernel_size // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:  # (B, D, J, T)
        B, D, J, T = x.shape
        k = self.temporal.kernel_size[0]
        # oneDNN convolves channels-last memory faster than NCHW (a 6 s decode: 10.3 against 11.0 ms)
        x = x.contiguous(memory_format=torch.channels_last)
        # The joint's own linear term is the temporal kernel's centre tap: fold it in.
        w = self.temporal.weight.clone()
        w[:, :, k // 2] += self.self_proj.weight
        out = F.conv2d(x, w.unsqueeze(2), self.temporal.bias + self.self_proj.bias, padding=(0, k // 2))
        # channels-last memory is (B, J, T, D): averaging over neighbouring joints is one matmul on it
        neighbours = torch.matmul(self.neighbour_mean, x.permute(0, 2, 3, 1).reshape(B, J, T * D))
        neighbours = neighbours.view(B, J, T, D).permute(0, 3, 1, 2)
        out = out + F.conv2d(neighbours, self.neighbour_proj.weight.view(D, D, 1, 1), self.neighbour_proj.bias)
        return out


class ResSTBlock(nn.Module):
    def __init__(self, level: sk.SkeletonLevel, dim: int, kernel_size: int, dropout: float):
        super().__init__()
        self.conv1 = STConv(level, dim, kernel_size)
        self.conv2 = STConv(level, dim, kernel_size)
        self.drop = nn.Dropout(dropout)

    def forward(self, x):
        return x + self.drop(self.conv2(F.gelu(self.conv1(F.gelu(x)))))


class STPool(nn.Module):
    """Average adjacent joints (topology-preserving) and pairs of frames."""

    def __init__(self, groups, n_fine: int):
        super().__init__()
        self.register_buffer("pool", torch.from_numpy(sk.pooling_matrix(groups, n_fine)), persistent=False)

    def forward(self, x):  # (B, D, J, T) -> (B, D, J', T/2)
        return F.avg_pool2d(torch.matmul(self.pool, x), kernel_size=(1, 2))


class STUnpool(nn.Module):
    """Inverse of STPool: each fine joint averages the coarse joints that cover it;
    frames are doubled by linear interpolation."""

    def __init__(self, groups, n_fine: int):
        super().__init__()
        self.register_buffer("unpool", torch.from_numpy(sk.unpooling_matrix(groups, n_fine)), persistent=False)

    def forward(self, x):  # (B, D, J', T) -> (B, D, J, 2T)
        x = torch.matmul(self.unpool, x)
        return F.interpolate(x, scale_factor=(1.0, 2.0), mode="bilinear", align_corners=False)


class PerJointLinear(nn.Module):
    """A separate linear map for each of J joints: (B, Din, J, T) -> (B, T, J, Dout)."""

    def __init__(self, joints: int, d_in: int, d_out: int):
        super().__init__()
        self.weight = nn.Parameter(torch.empty(joints, d_in, d_out))
        self.bias = nn.Parameter(torch.zeros(joints, d_out))
        bound = 1.0 / np.sqrt(d_in)
        nn.init.uniform_(self.weight, -bound, bound)
        nn.init.uniform_(self.bias, -bound, bound)

    def forward(self, x):
        return torch.einsum("bijt,jio->btjo", x, self.weight) + self.bias


class MotionVAE(nn.Module):
    def __init__(self, config: VAEConfig | None = None):
        super().__init__()
        self.config = c = config or VAEConfig()
        dims = _joint_dims(c.activation_channel)
        D, k = c.latent_dim, c.kernel_size
        j22, j12, j7 = sk.LEVELS

        self.joint_in = JointwiseMLP(dims, [D] * len(dims), D)
        self.enc22 = nn.Sequential(*[ResSTBlock(j22, D, k, c.dropout) for _ in range(c.blocks_per_level)])
        self.pool1 = STPool(sk.POOL_22_TO_12, j22.size)
        self.enc12 = nn.Sequential(*[ResSTBlock(j12, D, k, c.dropout) for _ in range(c.blocks_per_level)])
        self.pool2 = STPool(sk.POOL_12_TO_7, j12.size)
        self.to_dist = PerJointLinear(j7.size, D, 2 * D)

        if c.decoder_dim and c.decoder_dim < D:
            raise ValueError(f"decoder_dim must be 0 or at least latent_dim ({D}), got {c.decoder_dim}")
        Dd = self.decoder_dim = c.decoder_dim or D
        self.unpool2 = STUnpool(sk.POOL_12_TO_7, j12.size)
        self.dec12 = nn.Sequential(*[ResSTBlock(j12, Dd, k, c.dropout) for _ in range(c.blocks_per_level)])
        self.unpool1 = STUnpool(sk.POOL_22_TO_12, j22.size)
        self.dec22 = nn.Sequential(*[ResSTBlock(j22, Dd, k, c.dropout) for _ in range(c.blocks_per_level)])
        self.joint_out = JointwiseMLP([Dd] * len(dims), dims, Dd)

    # -- shapes
    @staticmethod
    def latent_frames(frames: int) -> int:
        if frames % 4:
            raise ValueError(f"the VAE needs a frame count divisible by 4, got {frames}")
        return frames // 4

    def _split(self, x: torch.Tensor, activation: torch.Tensor | None) -> list[torch.Tensor]:
        parts = rep.split_by_joint(x)
        if self.config.activation_channel:
            if activation is None:
                activation = torch.ones(x.shape[:-1], dtype=x.dtype, device=x.device)
            parts[0] = torch.cat((parts[0], activation.unsqueeze(-1).to(x.dtype)), dim=-1)
        return parts

    def encode(self, x: torch.Tensor, activation: torch.Tensor | None = None):
        """Normalised features (B, T, 263) [+ activation (B, T)] -> (mu, logvar), each (B, T/4, 7, D)."""
        if x.ndim != 3 or x.shape[-1] != rep.FEATURE_DIM:
            raise ValueError(f"expected features (B, T, {rep.FEATURE_DIM}), got {tuple(x.shape)}")
        self.latent_frames(x.shape[1])
        h = torch.stack(self.joint_in(self._split(x, activation)), dim=2).permute(0, 3, 2, 1)  # (B, D, 22, T)
        h = self.pool2(self.enc12(self.pool1(self.enc22(h.contiguous()))))
        mu, logvar = self.to_dist(h).chunk(2, dim=-1)
        return mu, logvar.clamp(-30.0, 20.0)

    def decode(self, z: torch.Tensor):
        """(B, T/4, 7, D) -> (features (B, T, 263), activation logits (B, T) or None)."""
        h = z.permute(0, 3, 2, 1)
        if self.decoder_dim > h.shape[1]:
            # the latent fills the first channels of a wider decoder's residual stream
            h = F.pad(h, (0, 0, 0, 0, 0, self.decoder_dim - h.shape[1]))
        h = self.dec22(self.unpool1(self.dec12(self.unpool2(h))))
        h = h.permute(0, 3, 2, 1)  # (B, T, 22, D)
        parts = self.joint_out([h[:, :, j] for j in range(h.shape[2])])
        act = None
        if self.config.activation_channel:
            act = parts[0][..., -1]
            parts[0] = parts[0][..., :-1]
        return rep.merge_joints(parts), act

    def forward(self, x, activation=None, sample: bool = True, eps: torch.Tensor | None = None,
                z_given: torch.Tensor | None = None, given_rows: torch.Tensor | None = None):
        """eps: the reparameterisation noise, (B, T/4, 7, D); drawn here when not given. Rows marked
        in given_rows (B,) decode z_given (B, T/4, 7, D) instead of their encoding (a decoder
        fine-tune on denoised latents: training/denoised_latents.py)."""
        mu, logvar = self.encode(x, activation)
        if sample:
            eps = torch.randn_like(mu) if eps is None else eps.to(mu.dtype)
            z = mu + eps * torch.exp(0.5 * logvar)
        else:
            z = mu
        if given_rows is not None:
            z = torch.where(given_rows.view(-1, 1, 1, 1), z_given.to(z.dtype), z)
        recon, act_logits = self.decode(z)
        return recon, act_logits, mu, logvar

    def loss(self, x, activation=None, valid=None, eps=None, z_given=None, given_rows=None):
        """SmoothL1 reconstruction in normalised space (+ ric and velocity terms), KL, and
        BCE on the activation logits. `valid` (B, T) masks frames after a motion's end
        out of the feature terms; the activation term sees every frame. z_given, given_rows: as in forward."""
        recon, act_logits, mu, logvar = self(x, activation, eps=eps, z_given=z_given, given_rows=given_rows)
        c = self.config
        if valid is None:
            valid = torch.ones(x.shape[:2], dtype=torch.bool, device=x.device)
        w = valid.to(x.dtype).unsqueeze(-1)
        denom = w.sum().clamp_min(1.0)

        def masked(sl):
            err = F.smooth_l1_loss(recon[..., sl], x[..., sl], reduction="none")
            return (err * w).sum() / (denom * err.shape[-1])

        terms = {
            "rec": masked(slice(None)),
            "pos": masked(rep.RIC_SLICE),
            "vel": masked(rep.VEL_SLICE),
            "kl": 0.5 * torch.mean(mu.pow(2) + logvar.exp() - logvar - 1.0),
        }
        total = terms["rec"] + c.lambda_pos * terms["pos"] + c.lambda_vel * terms["vel"] + c.lambda_kl * terms["kl"]
        if act_logits is not None:
            target = activation if activation is not None else torch.ones_like(act_logits)
            # BCE on logits: the decoder's raw output, never a sigmoid of it.
            terms["act"] = F.binary_cross_entropy_with_logits(act_logits, target.to(act_logits.dtype))
            total = total + c.lambda_act * terms["act"]
        terms["total"] = total
        return total, {k: float(v.detach()) for k, v in terms.items()}, recon, act_logits


# the modules that define the latent space, and those that only read it
ENCODER_PARTS = ("joint_in", "enc22", "pool1", "enc12", "pool2", "to_dist")
DECODER_PARTS = ("dec12", "dec22", "joint_out")


def widen_decoder(vae: MotionVAE, dim: int, init_std: float = 1e-2, seed: int = 0) -> MotionVAE:
    """A copy of `vae` whose decoder has `dim` channels and decodes exactly as before: the old
    channels keep their weights and never read the new ones; the new channels read everything
    through small random weights and are read by nothing yet, so training can put them to use
    without the decoder first unlearning what it knows. The encoder (the latent space) is unchanged."""
    from dataclasses import replace
    old_dim = vae.decoder_dim
    if dim < old_dim:
        raise ValueError(f"cannot narrow a decoder from {old_dim} to {dim} channels")
    wide = MotionVAE(replace(vae.config, decoder_dim=dim))
    g = torch.Generator().manual_seed(seed)
    source, state = vae.state_dict(), {}
    for name, new in wide.state_dict().items():
        old = source[name]
        if name.split(".", 1)[0] not in DECODER_PARTS or new.shape == old.shape:
            state[name] = old.clone()
            continue
        # rows are outputs, columns inputs; new rows of a weight read everything, new biases start at zero, and
        # the joint MLPs' last layer (outputs: features) only gains zero columns
        w = torch.zeros_like(new)
        if new.ndim > 1 and new.shape[0] > old.shape[0]:
            w[old.shape[0]:] = init_std * torch.randn(new[old.shape[0]:].shape, generator=g)
        w[tuple(slice(0, n) for n in old.shape)] = old
        state[name] = w
    wide.load_state_dict(state)
    return wide.train(vae.training)
