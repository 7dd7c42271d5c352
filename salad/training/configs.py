"""Training configurations (TOML files map onto these dataclasses one to one)."""
from __future__ import annotations

from dataclasses import dataclass, field

from ..config import require
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

    def check(self, where: str = "") -> None:
        require(self.window >= 4 and self.window % 4 == 0, where, "window", "a multiple of 4 from 4 on", self.window)
        require(self.max_frames >= 4 and self.max_frames % 4 == 0, where, "max_frames", "a multiple of 4 from 4 on",
                self.max_frames)
        require(1 <= self.min_frames <= self.max_frames, where, "min_frames", f"in 1..max_frames ({self.max_frames})",
                self.min_frames)
        check_balance(self.balance, where)


def check_balance(balance: float, where: str = "data.") -> float:
    """data.balance as given, refused outside [-1, 1]: 1 draws as recorded, 0 every class alike, below 0
    the rarer classes more often; beyond -1 a class of one take would crowd out the rest."""
    require(-1.0 <= balance <= 1.0, where, "balance", "in [-1, 1]", balance)
    return balance


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

    def check(self, where: str = "") -> None:
        require(self.lr > 0, where, "lr", "> 0", self.lr)
        require(len(self.betas) == 2 and all(0 <= b < 1 for b in self.betas), where, "betas", "two numbers in [0, 1)",
                self.betas)
        require(self.weight_decay >= 0, where, "weight_decay", ">= 0", self.weight_decay)
        require(self.warmup_steps >= 0, where, "warmup_steps", ">= 0", self.warmup_steps)
        require(all(isinstance(m, int) and m > 0 for m in self.milestones) and list(self.milestones) ==
                sorted(set(self.milestones)), where, "milestones", "ascending positive step counts", self.milestones)
        require(self.gamma > 0, where, "gamma", "> 0", self.gamma)
        require(self.batch_size >= 1, where, "batch_size", ">= 1", self.batch_size)
        require(self.max_steps >= 1, where, "max_steps", ">= 1", self.max_steps)
        require(self.grad_clip >= 0, where, "grad_clip", ">= 0 (0: no clipping)", self.grad_clip)


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

    def check(self, where: str = "") -> None:
        for name in ("checkpoint_every", "log_every"):
            require(getattr(self, name) >= 1, where, name, ">= 1", getattr(self, name))
        require(self.threads >= 0, where, "threads", ">= 0 (0: torch's default)", self.threads)
        require(self.validate_every >= 0, where, "validate_every", ">= 0 (0: off)", self.validate_every)


@dataclass
class VAETrainConfig:
    data: DataConfig = field(default_factory=DataConfig)
    model: VAEConfig = field(default_factory=VAEConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    run: RunConfig = field(default_factory=RunConfig)
    window_overhang: float = 0.5  # at most this fraction of a window may lie past a motion's end

    def check(self, where: str = "") -> None:
        require(0 <= self.window_overhang < 1, where, "window_overhang", "in [0, 1)", self.window_overhang)


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

    def check(self, where: str = "") -> None:
        for name in ("text_dropout", "auto_length_prob"):
            require(0 <= getattr(self, name) <= 1, where, name, "in [0, 1]", getattr(self, name))
        require(0 <= self.ema_decay < 1, where, "ema_decay", "in [0, 1) (0: no EMA)", self.ema_decay)
        require(self.min_snr_gamma >= 0, where, "min_snr_gamma", ">= 0 (0 = off)", self.min_snr_gamma)
        for name in ("contact_loss", "posterior_noise"):
            require(getattr(self, name) >= 0, where, name, ">= 0", getattr(self, name))
        require(self.anchor_max_clips >= 0, where, "anchor_max_clips", ">= 0", self.anchor_max_clips)


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
    # weight of the decoded bones' length error against the real clip's, m^2: keeps limbs their length in
    # poses the decoder rarely saw; 0 = off
    lambda_bone: float = 0.0
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

    def check(self, where: str = "") -> None:
        for name in ("lambda_adv", "lambda_foot", "lambda_root", "lambda_acc", "lambda_bone", "decoder_dim"):
            require(getattr(self, name) >= 0, where, name, ">= 0", getattr(self, name))
        require(0 <= self.denoised_share <= 1, where, "denoised_share", "in [0, 1]", self.denoised_share)
        require(0 <= self.window_overhang < 1, where, "window_overhang", "in [0, 1)", self.window_overhang)


# what a consistency student is taught to match (ConsistencyTrainConfig.target)
CONSISTENCY_TARGETS = ("lcd", "trajectory")
ADVERSARIAL_REAL = ("data", "teacher")


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
    # an adversarial term (0: off): a SAN discriminator, given the prompt, tells the student's clean
    # estimates from the batch's real motions; the student's share of its gradient is lambda_adv
    # times the consistency loss's, measured on the estimates at every step
    lambda_adv: float = 0.0
    # what the discriminator judges: "latents", or "motion" (both sides decoded by the teacher's VAE)
    adversarial_space: str = "latents"
    # what it takes as real: "data", the batch's own captures, or "teacher", the teacher's stochastic
    # samples (SDE-DPM-Solver++ on teacher_steps) of the batch's prompts (trajectory target only; one
    # more teacher sampling per solve)
    adversarial_real: str = "data"
    # the actions in focus: the discriminator judges their rows alone (lambda_adv > 0) and focus_rows gives
    # them rows of every solved batch. 0: no focus (every row judged); n > 0: the content classes with at most
    # n training clips (the rare actions, whose motions the plain student tames most), so the common classes
    # keep what the consistency loss gives them
    focus_max_clips: int = 0
    # or, instead, these content classes (e.g. ["kick", "slash"]: the rare actions the student still tames)
    focus_classes: list[str] = field(default_factory=list)
    # rows of every batch the teacher solves given to the actions in focus (drawn by the class balance among
    # them); 0: only those the batch happens to draw. A run solves one batch in `replay` steps (nine in 100
    # steps at replay = 12), so otherwise how many of them are judged is mostly the seed. With lambda_adv = 0
    # nothing judges them: the rows only give the consistency loss more of those actions' solves (a fresh
    # distillation sees a few hundred solved kicks in 2,000 steps otherwise).
    focus_rows: int = 0
    # the share of rows whose caption is crossed with another row's at a word both use (e.g. "a man kicks with
    # one leg" x "a guy waves with his right hand" -> "a man kicks with his right hand"), so that the teacher's
    # reading of wordings no clip is captioned with is distilled too, not only the training captions' (session 65:
    # a 300-step fine-tune at 0.5 read two misread kick paraphrases as kicks more often, but kicked lower).
    # Trajectory target only (its solves start from noise, so a crossed caption need not describe the row's
    # capture); crossed rows are not judged by a discriminator of data.
    caption_crossover: float = 0.0
    # from this step on, each checkpoint's student is judged on the actions in focus (the fidelity checks of
    # motions made from their training captions, salad.eval.fidelity.validate_actions; every judgement goes
    # to val.jsonl) and model/ keeps the best one; 0: model/ is the last checkpoint. Session 73 saw one
    # adversarial stage's kick swing 0.2-0.4 m between checkpoints 50 steps apart.
    select_from: int = 0
    # how many of each judged action's training captions the judgement draws motions from (8 seeds each; an
    # action with fewer takes them all): more captions rank checkpoints more as the held-out paraphrases do,
    # at ~0.1 s a motion on two threads (24 captions x 6 actions: 100-113 s a checkpoint in session 76's run)
    select_captions: int = 4
    # its network (feature_dim is set from what it judges and the text projection)
    discriminator: DiscriminatorConfig = field(default_factory=lambda: DiscriminatorConfig(levels=1))

    def check(self, where: str = "") -> None:
        require(0 <= self.guidance_min <= self.guidance_max, where, "guidance_min",
                f"in [0, guidance_max ({self.guidance_max})]", self.guidance_min)
        require(self.huber_c > 0, where, "huber_c", "> 0", self.huber_c)
        require(0 <= self.auto_length_prob <= 1, where, "auto_length_prob", "in [0, 1]", self.auto_length_prob)
        require(0 < self.target_decay < 1, where, "target_decay", "in (0, 1)", self.target_decay)
        require(self.target in CONSISTENCY_TARGETS, where, "target", f"one of {', '.join(CONSISTENCY_TARGETS)}",
                self.target)
        require(2 <= self.teacher_steps <= 200, where, "teacher_steps", "in 2..200", self.teacher_steps)
        for name in ("replay", "replay_buffer"):
            require(getattr(self, name) >= 1, where, name, ">= 1", getattr(self, name))
        require(0 <= self.cfg_rescale <= 1, where, "cfg_rescale", "in [0, 1]", self.cfg_rescale)
        require(0 <= self.cfg_cutoff < 1, where, "cfg_cutoff", "in [0, 1)", self.cfg_cutoff)
        require(self.lambda_adv >= 0, where, "lambda_adv", ">= 0", self.lambda_adv)
        require(self.adversarial_space in ("latents", "motion"), where, "adversarial_space",
                "latents or motion", self.adversarial_space)
        require(self.adversarial_real in ADVERSARIAL_REAL, where, "adversarial_real",
                f"one of {', '.join(ADVERSARIAL_REAL)}", self.adversarial_real)
        require(self.adversarial_real == "data" or self.target == "trajectory", where, "adversarial_real",
                '"data" with target = "lcd" (the teacher\'s samples come with its solves)', self.adversarial_real)
        require(self.focus_max_clips >= 0, where, "focus_max_clips", ">= 0", self.focus_max_clips)
        require(not (self.focus_classes and self.focus_max_clips), where, "focus_classes",
                "empty when focus_max_clips picks the actions", self.focus_classes)
        require(0 <= self.focus_rows <= self.optim.batch_size, where, "focus_rows",
                f"in 0..optim.batch_size ({self.optim.batch_size})", self.focus_rows)
        require(not self.focus_rows or self.focus_classes or self.focus_max_clips,
                where, "focus_rows", "0 unless focus_classes or focus_max_clips names the actions",
                self.focus_rows)
        require(0 <= self.caption_crossover <= 1, where, "caption_crossover", "in [0, 1]", self.caption_crossover)
        require(self.select_captions >= 1, where, "select_captions", ">= 1", self.select_captions)
        require(0 <= self.select_from <= self.optim.max_steps, where, "select_from",
                f"in 0..optim.max_steps ({self.optim.max_steps})", self.select_from)
        require(not self.select_from or self.focus_classes or self.focus_max_clips, where, "select_from",
                "0 unless focus_classes or focus_max_clips names the actions it judges", self.select_from)
        require(not self.select_from or not self.data.bundle, where, "select_from",
                "0 with a latent bundle (data.bundle): it reads captions and captures from data.root",
                self.select_from)
        require(not self.caption_crossover or self.target == "trajectory", where, "caption_crossover",
                '0 with target = "lcd" (its rows are noised captures, which a crossed caption no longer describes)',
                self.caption_crossover)
