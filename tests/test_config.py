import dataclasses
import re
from argparse import Namespace
from pathlib import Path

import pytest
import torch

from salad.checkpoint import save_checkpoint
from salad.config import ConfigError, apply_overrides, from_dict, load_toml
from salad.eval.selection import best_score
from salad.models.denoiser import Denoiser
from salad.training.configs import DenoiserTrainConfig


def test_nested_tables_keep_the_configs_own_defaults():
    cfg = from_dict(DenoiserTrainConfig, {"optim": {"batch_size": 8}, "run": {"seed": 3}})
    assert cfg.optim.batch_size == 8 and cfg.optim.lr == 5e-4 and cfg.optim.weight_decay == 1e-6
    assert cfg.run.out_dir == "runs/denoiser" and cfg.run.seed == 3


def test_unknown_keys_and_wrong_types_are_errors():
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(DenoiserTrainConfig, {"optim": {"learning_rate": 1.0}})
    with pytest.raises(ConfigError, match="expected int"):
        from_dict(DenoiserTrainConfig, {"optim": {"batch_size": "big"}})


def test_command_line_overrides_win_only_where_given():
    cfg = from_dict(DenoiserTrainConfig, {"data": {"root": "a"}})
    apply_overrides(cfg, Namespace(out_dir="o", max_steps=None, data=None, threads=2))
    assert (cfg.run.out_dir, cfg.optim.max_steps, cfg.data.root, cfg.run.threads) == ("o", DenoiserTrainConfig().optim.max_steps, "a", 2)
    assert cfg.data.balance == 1.0                                     # not given: the file's
    apply_overrides(cfg, Namespace(balance=0.0))                       # 0 (every class alike) is a value, not "unset"
    assert cfg.data.balance == 0.0
    cfg.run.seed = 3
    apply_overrides(cfg, Namespace(seed=None))
    assert cfg.run.seed == 3
    apply_overrides(cfg, Namespace(seed=0))                            # so is seed 0
    assert cfg.run.seed == 0


CONFIGS = sorted((Path(__file__).resolve().parents[1] / "configs").glob("*.toml"))


def _config_class(what: str):
    from salad.training.classifier_task import ClassifierTrainConfig
    from salad.training.configs import ConsistencyTrainConfig, VAESANTrainConfig, VAETrainConfig
    from salad.training.evaluator_task import EvaluatorTrainConfig
    return {"vae": VAETrainConfig, "vae-san": VAESANTrainConfig, "denoiser": DenoiserTrainConfig,
            "consistency": ConsistencyTrainConfig, "classifier": ClassifierTrainConfig,
            "evaluator": EvaluatorTrainConfig}[what]


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_every_shipped_config_loads_with_the_command_its_header_names(path):
    # Each file's comment says how to reproduce it ("salad train WHAT --config configs/NAME"); a config
    # that no longer loads, or a header that names the wrong trainer, would only show when someone runs it.
    header = " ".join(line.lstrip("#").strip() for line in path.read_text(encoding="utf-8").splitlines()
                      if line.startswith("#")).replace("\\ ", "")
    found = re.search(rf"salad train ([a-z-]+)\s+--config configs/{re.escape(path.name)}", header)
    assert found, f"{path.name}: its header does not name the `salad train ... --config` command that uses it"
    cfg = load_toml(_config_class(found.group(1)), path)
    if isinstance(cfg, DenoiserTrainConfig):
        Denoiser(cfg.model)      # widths that do not fit one another fail here, not hours into a run


@pytest.mark.parametrize("table, key, value, message", [
    ("optim", "batch_size", "0", "optim.batch_size must be >= 1, got 0"),
    ("optim", "lr", "-1e-4", "optim.lr must be > 0"),
    ("optim", "milestones", "[500, 100]", "optim.milestones must be ascending positive step counts"),
    ("run", "log_every", "0", "run.log_every must be >= 1, got 0"),
    ("data", "window", "30", "data.window must be a multiple of 4"),
    ("data", "min_frames", "400", "data.min_frames must be in 1..max_frames (196)"),
    (None, "text_dropout", "1.5", "text_dropout must be in [0, 1], got 1.5"),
])
def test_a_value_out_of_range_names_its_file_and_field_when_the_config_loads(tmp_path, table, key, value, message):
    # Without the rules these ran: a zero log_every or batch size failed at the first step, after
    # minutes of loading data and text features; a dropout of 1.5 trained a model that never saw a caption.
    path = tmp_path / "bad.toml"
    path.write_text(f"[{table}]\n{key} = {value}\n" if table else f"{key} = {value}\n")
    with pytest.raises(ConfigError) as caught:
        load_toml(DenoiserTrainConfig, path)
    assert str(caught.value).startswith(f"{path}: ") and message in str(caught.value)


def test_overrides_and_configs_built_in_code_are_held_to_the_same_rules(tmp_path):
    from salad.training.configs import OptimConfig, RunConfig
    from salad.training.loop import Trainer

    cfg = from_dict(DenoiserTrainConfig, {})
    with pytest.raises(ConfigError, match="optim.max_steps must be >= 1, got -5"):
        apply_overrides(cfg, Namespace(max_steps=-5))
    with pytest.raises(ConfigError, match="run.threads must be >= 0"):
        apply_overrides(from_dict(DenoiserTrainConfig, {}), Namespace(threads=-2))
    # a trainer refuses them before it touches the task (here: none at all) or the run directory
    with pytest.raises(ConfigError, match="optim.grad_clip must be >= 0"):
        Trainer(None, OptimConfig(grad_clip=-1.0), RunConfig(out_dir=str(tmp_path / "run")))
    with pytest.raises(ConfigError, match="run.checkpoint_every must be >= 1"):
        Trainer(None, OptimConfig(), RunConfig(out_dir=str(tmp_path / "run"), checkpoint_every=0))
    assert not (tmp_path / "run").exists()


def test_the_command_line_reports_a_bad_config_without_starting(tiny_dataset, tmp_path, capsys):
    from salad.cli import main

    cfg = tmp_path / "v.toml"
    cfg.write_text(f'[data]\nroot = "{tiny_dataset}"\n[run]\nout_dir = "{tmp_path / "run"}"\ncheckpoint_every = 0\n')
    assert main(["train", "vae", "--config", str(cfg)]) == 2
    assert "run.checkpoint_every must be >= 1, got 0" in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


@dataclasses.dataclass
class _Optim:
    lr: float = 1e-3
    max_steps: int = 100


@dataclasses.dataclass
class _Run:
    threads: int = 2


@dataclasses.dataclass
class _Judged:
    optim: _Optim = dataclasses.field(default_factory=_Optim)
    run: _Run = dataclasses.field(default_factory=_Run)
    focus_rows: int = 4
    select_captions: int = 4


def test_a_kept_best_score_counts_only_for_a_run_of_the_same_model(tmp_path):
    # stored by an older run: an old key name, and no select_captions (added since)
    stored = {"optim": {"lr": 1e-3, "max_steps": 100}, "run": {"threads": 2}, "adversarial_rows": 4}
    save_checkpoint(tmp_path / "best", "classifier", {}, {"model": {"w": torch.zeros(1)}},
                    {"val": {"score": 0.75}, "train_config": stored})
    # run settings, a longer schedule, a key's new name and a field at its default make the same model
    same = _Judged(optim=_Optim(max_steps=900), run=_Run(threads=1))
    assert best_score(tmp_path / "best", "classifier", same) == 0.75
    for other in (_Judged(optim=_Optim(lr=2e-3)), _Judged(focus_rows=8), _Judged(select_captions=24)):
        assert best_score(tmp_path / "best", "classifier", other) == float("-inf")
    assert best_score(tmp_path / "missing", "classifier", same) == float("-inf")
