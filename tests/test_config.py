from argparse import Namespace

import pytest

from salad.config import ConfigError, apply_overrides, from_dict
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
