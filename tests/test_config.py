import pytest

from salad.config import ConfigError, from_dict
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
