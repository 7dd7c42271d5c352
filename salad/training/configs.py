"""Training configurations (TOML files map onto these dataclasses one to one)."""
from __future__ import annotations

from dataclasses import dataclass, field

from ..diffusion.schedule import DiffusionConfig
from ..models.denoiser import DenoiserConfig
from ..models.discriminator import DiscriminatorConfig
from ..models.vae import VAEConfig


@dataclass
class DataConfig:
    root: str = "data/bandai-hml"
    min_frames: int = 16
    max_frames: int = 196        # 9.8 s at 20 fps: the longest motion (and the auto-length canvas)
    window: int = 64             # VAE training windows
    # How often each content class (labels.json) is drawn, as (its clip count)^balance: 1 = as
    # recorded; 0.5 = square root, so an action recorded 4 times is drawn 1/12 as often as one
    # recorded 600 times instead of 1/150; 0 = every class alike; below 0 (down to -1) the rarer a
    # class, the more often it is drawn. The VAE draws windows: there a class's share is (its frame
    # count)^balance, and a motion's within it its share of the frames.
    balance: float = 1.0
    # denoiser (and consistency) training only: a latent bundle (`salad data bundle`) to train from
    # instead of root's features and the text encoder, e.g. on a GPU machine the dataset cannot reach
    bundle: str = ""


@dataclass
class OptimConfig:
    lr: float = 2e-4
    betas: tuple = (0.9, 0.99)
    weight_decay: float = 0.0
    warmup_steps: int = 2000
    milestones: tuple = ()        # steps at which the learning rate is multiplied by gamma
    gamma: float = 0.1
    batch_size: int = 64          # per process
    max_steps: int = 20000
    grad_clip: float = 1.0


@dataclass
class RunConfig:
    out_dir: str = "runs/vae"
    seed: int = 0
    bf16: bool = True             # bf16 autocast: ~1.5-4x faster matmuls on CPUs with AVX-512 BF16
    checkpoint_every: int = 500
    log_every: int = 50
    threads: int = 0              # 0 = torch's default
    device: str = "auto"          # auto (a CUDA GPU when present, else the CPU), cpu, cuda or cuda:N
    # steps between losses on the validation split, logged as val_loss (tasks that have one; 0 = off)
    validate_every: int = 0


@dataclass
class VAETrainConfig:
    data: DataConfig = field(default_factory=DataConfig)
    model: VAEConfig = field(default_factory=VAEConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    run: RunConfig = field(default_factory=RunConfig)
    window_overhang: float = 0.5  # at most this fraction of a window may lie past a motion's end


@dataclass
class DenoiserTrainConfig:
    data: DataConfig = field(default_factory=DataConfig)
    model: DenoiserConfig = field(default_factory=DenoiserConfig)
    diffusion: DiffusionConfig = field(default_factory=DiffusionConfig)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=5e-4, betas=(0.9, 0.99), weight_decay=1e-6))
    run: RunConfig = field(default_factory=lambda: RunConfig(out_dir="runs/denoiser"))
    vae: str = "runs/vae/model"   # the trained VAE checkpoint the latents come from
    text_encoder: str = "minilm"
    text_dropout: float = 0.1     # probability of training on the empty prompt (for CFG)
    auto_length_prob: float = 0.5 # share of samples drawn on the full canvas with an activation tail
    ema_decay: float = 0.999
    # weight of the planted feet's world-velocity error of the decoded clean estimate (m/s)^2
    # (training/foot_loss.py); 0 = off
    contact_loss: float = 0.0
    # the latents are mu + posterior_noise * sigma * eps of the VAE's posterior; 0 trains on the means, whose
    # motion decodes without the frame-to-frame tremor that the posterior's noise becomes in the decoder
    posterior_noise: float = 1.0
    # Min-SNR-gamma loss weighting (Hang et al. 2023): each timestep's loss rescaled to the clean sample's and
    # capped at gamma; 0 = off (every timestep alike, as the shipped denoiser trained)
    min_snr_gamma: float = 0.0
    # Fine-tuning that teaches the rare actions and keeps the rest: a denoiser checkpoint directory whose
    # predictions become the target of every row of a content class with more than anchor_max_clips training
    # clips (those rows learn to predict what the anchor does at the same noisy latent, timestep and caption);
    # rows of the rarer classes learn from the data as usual. "" = off (every row learns from the data)
    anchor: str = ""
    anchor_max_clips: int = 4


@dataclass
class VAESANTrainConfig:
    """Adversarial fine-tuning of a trained VAE's decoder; its encoder and latent scale stay
    frozen, so a denoiser trained on `vae`'s latents works with the result."""
    vae: str = "assets/model/vae"     # the VAE whose latent space is kept (read only)
    lambda_adv: float = 1e-3          # MoLA's weight of the adversarial term; 0 = plain fine-tuning
    # weights of the planted feet's and of the root's world-velocity error, (m/s)^2 (training/foot_loss.py); 0 = off
    lambda_foot: float = 0.0
    lambda_root: float = 0.0
    # weight of the joints' world acceleration error, (m/s^2)^2: keeps latent noise from becoming jitter; 0 = off
    lambda_acc: float = 0.0
    # the decoder's channel width: 0 keeps the source's; more widens it, decoding exactly as the source's
    # does at the start (models/vae.py: widen_decoder)
    decoder_dim: int = 0
    # latents the model's denoisers made from training clips (`salad data denoised-latents`), and the share of
    # each batch decoded from them and held to the real clip instead of a posterior sample; "" = none
    denoised_latents: str = ""
    denoised_share: float = 0.5
    data: DataConfig = field(default_factory=DataConfig)
    discriminator: DiscriminatorConfig = field(default_factory=DiscriminatorConfig)
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=1e-4, warmup_steps=100, grad_clip=0.0))
    run: RunConfig = field(default_factory=lambda: RunConfig(out_dir="runs/vae_san"))
    window_overhang: float = 0.5


@dataclass
class ConsistencyTrainConfig:
    """Latent consistency distillation of a trained denoiser (the teacher, with classifier-free
    guidance) into a student that samples in 1-4 steps with the guidance scale as a condition."""
    teacher: str = "assets/model"     # a model directory (vae/ + denoiser/); read only
    guidance_min: float = 2.0         # the CFG scales the student learns, drawn uniformly per sample
    guidance_max: float = 10.0
    huber_c: float = 0.001            # pseudo-Huber loss on the latents (LCM's choice)
    auto_length_prob: float = 0.3
    data: DataConfig = field(default_factory=lambda: DataConfig(balance=0.5))
    optim: OptimConfig = field(default_factory=lambda: OptimConfig(lr=2e-4, warmup_steps=100, batch_size=32,
                                                                    max_steps=6000))
    run: RunConfig = field(default_factory=lambda: RunConfig(out_dir="runs/consistency", checkpoint_every=100,
                                                              log_every=10))
    target_decay: float = 0.95        # EMA of the student that gives the distillation target; it is exported
    # "lcd": the student at t is pulled to the target network at t - 20 after one teacher DDIM step
    # (LCM's bootstrapped objective). "trajectory": the teacher solves each noise draw all the way
    # down (DPM-Solver++ on `teacher_steps`, through every timestep the 1-4 step sampler visits) and
    # the student at those timesteps regresses the solution directly: no bootstrap chain to
    # propagate, so it needs far fewer steps, which is what a CPU can give.
    target: str = "lcd"
    teacher_steps: int = 25
    replay: int = 4                   # optimiser steps per teacher solve (trajectory only)
    replay_buffer: int = 16           # recent solves the replayed steps draw from
    # the teacher's guidance as the student learns it: rescaled (sampling.cfg_combine) and none
    # below cfg_cutoff x T, as the pipeline's teacher sampling does (0, 0: plain CFG at every step)
    cfg_rescale: float = 0.0
    cfg_cutoff: float = 0.0
    # an exported student to start from, of any width (e.g. a d = 128 student for a widened teacher, so
    # that sampling stays fast); empty: the teacher's own architecture and weights
    student: str = ""
