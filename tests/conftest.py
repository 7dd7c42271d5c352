import json
import os
import shutil
import socket
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


REPO = Path(__file__).resolve().parents[1]


def shared_data_dir() -> Path | None:
    env = os.environ.get("SALAD_SHARED_DATA")
    for cand in ([Path(env)] if env else []) + [REPO.parent / "shared" / "data"]:
        if cand.is_dir():
            return cand
    return None


@pytest.fixture
def cli(capsys):
    """cli(*args) -> (exit code, stderr) of the `salad` command run in this process: the same
    main() as `python -m salad.cli`, without the seconds a fresh interpreter takes to import torch."""
    from salad.cli import main

    def run(*args: str) -> tuple[int, str]:
        capsys.readouterr()
        try:
            code = main(list(args))
        except SystemExit as e:          # argparse refusals
            code = e.code
        return code, capsys.readouterr().err
    return run


@pytest.fixture(scope="session")
def shared_data() -> Path:
    d = shared_data_dir()
    if d is None:
        pytest.skip("../shared/data is not present")
    return d


@pytest.fixture(scope="session")
def hml_sample(shared_data):
    d = shared_data / "humanml3d-sample"
    return {
        "features": np.load(d / "new_joint_vecs" / "012314.npy"),
        "joints": np.load(d / "new_joints" / "012314.npy"),
        "mean": np.load(d / "Mean.npy"),
        "std": np.load(d / "Std.npy"),
    }


def synthetic_walk(frames: int = 60, seed: int = 0, speed: float = 1.2, turn: float = 0.0) -> np.ndarray:
    """A plausible walking skeleton (T, 22, 3) in metres, built from bone directions, for
    tests that must not depend on outside data."""
    from salad.motion import skeleton as sk
    from salad.motion.representation import forward_kinematics
    import torch
    from salad.motion.quaternion import yaw_quat

    rng = np.random.default_rng(seed)
    lengths = np.array([0, .11, .11, .12, .38, .38, .14, .40, .40, .06, .14, .14,
                        .22, .12, .12, .10, .12, .12, .26, .26, .25, .25])
    t = np.arange(frames) / 20.0
    phase = 2 * np.pi * 1.8 * t / 2
    quats = np.zeros((frames, 22, 4))
    quats[..., 0] = 1.0
    heading = turn * t
    quats[:, 0] = yaw_quat(torch.from_numpy(heading)).numpy()

    def swing(angle):  # rotation about +X
        return np.stack([np.cos(angle / 2), np.sin(angle / 2), 0 * angle, 0 * angle], -1)

    quats[:, 1] = swing(0.4 * np.sin(phase))
    quats[:, 2] = swing(-0.4 * np.sin(phase))
    quats[:, 4] = swing(-0.3 * np.clip(np.sin(phase + 1), 0, None))
    quats[:, 5] = swing(-0.3 * np.clip(np.sin(-phase + 1), 0, None))
    quats[:, 16] = swing(-0.3 * np.sin(phase))
    quats[:, 17] = swing(0.3 * np.sin(phase))
    quats[:, 18] = swing(-0.2 - 0.1 * rng.random(frames))
    quats[:, 19] = swing(-0.2 - 0.1 * rng.random(frames))
    offsets = torch.from_numpy(sk.RAW_OFFSETS * lengths[:, None])
    fwd = np.stack([np.sin(heading), 0 * t, np.cos(heading)], -1)
    root = np.cumsum(fwd * speed / 20.0, axis=0)
    root[:, 1] = 0.93 + 0.02 * np.sin(2 * phase)
    j = forward_kinematics(torch.from_numpy(quats), torch.from_numpy(root), offsets).numpy()
    j[..., 1] -= j[..., 1].min()
    return j.astype(np.float32)


def mp4_frames(path) -> np.ndarray:
    """Every frame of an MP4 (T, H, W, 3)."""
    import imageio.v2 as imageio

    with imageio.get_reader(path, format="FFMPEG") as reader:
        return np.stack([frame for frame in reader.iter_data()])


def write_tiny_dataset(root: Path, n: int = 12, frames: int = 72) -> Path:
    """A HumanML3D-layout directory of synthetic walks (straight, turning, mirrored)
    with captions, splits and statistics."""
    from salad.data.captions import caption_line
    from salad.motion import representation as rep

    root = Path(root)
    for sub in ("new_joint_vecs", "new_joints", "texts"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    names, feats = [], []
    for i in range(n):
        turn = (-0.6, 0.0, 0.6)[i % 3]
        speed = 0.8 + 0.1 * (i % 4)
        j = rep.canonicalize(synthetic_walk(frames + 1 + 4 * (i % 3), seed=i, speed=speed, turn=turn).astype(np.float64))
        f = rep.joints_to_features(j).astype(np.float32)
        name = f"{i:06d}"
        np.save(root / "new_joint_vecs" / f"{name}.npy", f)
        np.save(root / "new_joints" / f"{name}.npy", rep.features_to_joints(f).astype(np.float32))
        what = {-0.6: "turns right while walking", 0.0: "walks forward", 0.6: "turns left while walking"}[turn]
        caps = [f"a person {what}", f"someone {what} at {speed:.1f} metres per second"]
        (root / "texts" / f"{name}.txt").write_text("\n".join(caption_line(c) for c in caps) + "\n")
        names.append(name)
        feats.append(f)
    (root / "train.txt").write_text("\n".join(names[: n - 4]) + "\n")
    (root / "val.txt").write_text("\n".join(names[n - 4: n - 2]) + "\n")
    (root / "test.txt").write_text("\n".join(names[n - 2:]) + "\n")
    mean, std = rep.feature_statistics(np.concatenate(feats[: n - 4]))
    np.save(root / "Mean.npy", mean)
    np.save(root / "Std.npy", std)
    return root


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    return write_tiny_dataset(tmp_path_factory.mktemp("tiny-hml"))


@pytest.fixture(scope="session")
def tiny_model(tiny_dataset, tmp_path_factory) -> Path:
    """A tiny VAE + denoiser trained for a few steps on `tiny_dataset`: a real model directory
    that loads with load_pipeline, built once per test session."""
    from salad.diffusion.schedule import DiffusionConfig
    from salad.models.denoiser import DenoiserConfig
    from salad.models.vae import VAEConfig
    from salad.training.configs import DataConfig, DenoiserTrainConfig, OptimConfig, RunConfig, VAETrainConfig
    from salad.training.denoiser_task import DenoiserTask
    from salad.training.loop import Trainer
    from salad.training.vae_task import VAETask

    root = tmp_path_factory.mktemp("tiny-model")
    vcfg = VAETrainConfig(data=DataConfig(root=str(tiny_dataset), window=16),
                          model=VAEConfig(latent_dim=8, dropout=0.0),
                          optim=OptimConfig(lr=1e-3, warmup_steps=2, batch_size=4, max_steps=4),
                          run=RunConfig(out_dir=str(root / "vae-run"), bf16=False, checkpoint_every=4))
    Trainer(VAETask(vcfg), vcfg.optim, vcfg.run).fit()
    dcfg = DenoiserTrainConfig(
        data=DataConfig(root=str(tiny_dataset), max_frames=40),
        model=DenoiserConfig(latent_dim=8, dim=32, heads=4, ff_dim=64, layers=3, text_dim=384),
        diffusion=DiffusionConfig(),
        optim=OptimConfig(lr=1e-3, warmup_steps=2, batch_size=4, max_steps=4),
        run=RunConfig(out_dir=str(root / "den-run"), bf16=True, checkpoint_every=4),
        vae=str(root / "vae-run" / "model"))
    task = DenoiserTask(dcfg, show_progress=False)
    Trainer(task, dcfg.optim, dcfg.run, ema_decay=dcfg.ema_decay).fit()
    model = root / "model"
    model.mkdir()
    (model / "vae").symlink_to(root / "vae-run" / "model")
    (model / "denoiser").symlink_to(root / "den-run" / "model")
    return model


# the [run] table of the tiny training configs: fp32, a checkpoint every 2 steps, a log row every step
TINY_RUN = """[run]
bf16 = false
checkpoint_every = 2
log_every = 1
"""


def denoiser_toml(path: Path, root: Path, steps: int) -> Path:
    """A tiny denoiser config (its VAE comes from --vae)."""
    path.write_text(f"""vae = "does/not/exist"
[data]
root = "{root}"
max_frames = 40
[model]
latent_dim = 8
dim = 32
heads = 4
ff_dim = 64
layers = 3
text_dim = 384
[optim]
lr = 1e-3
warmup_steps = 4
batch_size = 4
max_steps = {steps}
""" + TINY_RUN)
    return path


def consistency_toml(path, data, teacher, steps, extra: str = ""):
    """A consistency-distillation config for the tiny model (`extra`: more top-level lines)."""
    path.write_text(f"""teacher = "{teacher}"
guidance_min = 2.0
guidance_max = 8.0
{extra}
[data]
root = "{data}"
max_frames = 40
balance = 1.0
[optim]
lr = 1e-3
warmup_steps = 1
batch_size = 4
max_steps = {steps}
""" + TINY_RUN)
    return path


@pytest.fixture(scope="session")
def tiny_student(tiny_model, tiny_dataset, tmp_path_factory):
    """The tiny model with a student distilled for a few steps through the CLI, in a copy of the
    model directory (the shared tiny model stays without one)."""
    from salad.cli import main

    root = tmp_path_factory.mktemp("student")
    cfg = consistency_toml(root / "c.toml", tiny_dataset, tiny_model, steps=3)
    assert main(["train", "consistency", "--config", str(cfg), "--out-dir", str(root / "run")]) == 0
    model = root / "model"
    model.mkdir()
    for part in ("vae", "denoiser"):
        (model / part).symlink_to((tiny_model / part).resolve())
    shutil.copytree(root / "run" / "model", model / "consistency")
    return model


@pytest.fixture(scope="session")
def pipe(tiny_model):
    """The tiny model's pipeline, loaded once and shared by the studio tests. It decodes without
    latent projection: the tiny VAE, trained for seconds, maps every motion to nearly the same one,
    which would hide what the studio's edits change; and without the planted-feet refinement, whose
    L-BFGS through that VAE would only add time here (its tests load their own pipelines)."""
    from salad.pipeline import load_pipeline

    pipe = load_pipeline(tiny_model)
    pipe.set_projections(0)
    pipe.set_foot_refine(0)
    return pipe


@contextmanager
def serve_studio(pipe, tmp_dir: Path, **settings):
    """A studio over `pipe` on a free local port, served in background threads; yields
    (url, StudioApp) and closes it (server and temp root) afterwards."""
    from app.server import create_app, launch
    from app.settings import Settings

    config = Settings(port=free_port(), tmp_dir=tmp_dir, concurrency=2, **settings)
    studio_app = create_app(config, pipe=pipe)
    try:
        yield launch(studio_app, config, block=False), studio_app
    finally:
        studio_app.close()


@pytest.fixture(scope="session", autouse=True)
def _no_client_download_leftovers():
    """gradio_client leaves an empty temp folder per downloaded file; the suite cleans up after itself."""
    import time

    from app.bench import remove_download_leftovers

    started = time.time()
    yield
    remove_download_leftovers(started)


@pytest.fixture
def client(server, tmp_path):
    """An API client of the test module's `server` fixture, downloading into tmp_path."""
    from gradio_client import Client

    return Client(server[0], verbose=False, download_files=str(tmp_path), analytics_enabled=False)


BANDAI_SUBSET = (
    "Bandai-Namco-Research-Motiondataset-1/data/dataset-1_bye_happy_001",
    "Bandai-Namco-Research-Motiondataset-1/data/dataset-1_walk_normal_002",
    "Bandai-Namco-Research-Motiondataset-2/data/dataset-2_wave-left-hand_active_001",
    "Bandai-Namco-Research-Motiondataset-2/data/dataset-2_wave-left-hand_active_011",  # truncated: 19 frames
    "Bandai-Namco-Research-Motiondataset-2/data/dataset-2_walk-turn-right_elderly_001",
    "Bandai-Namco-Research-Motiondataset-2/data/dataset-2_raise-up-both-hands_exhausted_001",
    "Bandai-Namco-Research-Motiondataset-2/data/dataset-2_walk-turn-right_masculine_007",  # turns left
)


@pytest.fixture(scope="session")
def bandai_subset(shared_data, tmp_path_factory) -> Path:
    """A few real Bandai clips (BVH + JSON + label files) in the archive's own layout,
    streamed out of the archive once per session."""
    import tarfile

    archive = shared_data / "bandai-motiondataset-dev.tar.xz"
    if not archive.is_file():
        pytest.skip(f"{archive} is not present")
    out = tmp_path_factory.mktemp("bandai-subset")
    wanted = {f"{m}{ext}" for m in BANDAI_SUBSET for ext in (".bvh", ".json")}
    with tarfile.open(archive, "r|xz") as tar:
        for member in tar:
            rel = member.name.split("dataset/", 1)[-1]
            if member.isfile() and (rel in wanted or "/cfg/" in rel):
                dest = out / rel
                dest.parent.mkdir(parents=True, exist_ok=True)
                dest.write_bytes(tar.extractfile(member).read())
                wanted.discard(rel)
    assert not wanted, f"archive lacks {sorted(wanted)}"
    return out


def labelled_copy(tiny_dataset, where: Path, kicks: int) -> Path:
    """tiny_dataset with labels.json: its first `kicks` training motions re-captioned as kicks."""
    from salad.data.captions import caption_line

    root = where / "labelled"
    shutil.copytree(tiny_dataset, root)
    names = (root / "train.txt").read_text().split()
    labels = {}
    for i, name in enumerate(names):
        content = "kick" if i < kicks else "walk"
        labels[name] = {"content": content, "style": "normal", "mirrored": False, "split": "train"}
        if content == "kick":
            (root / "texts" / f"{name}.txt").write_text(caption_line("a person kicks") + "\n")
    (root / "labels.json").write_text(json.dumps(labels))
    return root
