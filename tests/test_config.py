import re
from argparse import Namespace
from pathlib import Path

import pytest

from salad.config import ConfigError, apply_overrides, from_dict, load_toml
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
