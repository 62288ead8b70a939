"""TrainConfig validation: defaults, unknown keys and bad values name the key `train.<key>`; `train_config` takes
a Config (its typed section) or a raw mapping."""

import re

import pytest

from agents.config import TrainConfig, train_config
from cosim.config import load_config
from cosim.errors import ConfigError


def test_defaults_from_an_empty_section() -> None:
    assert train_config(load_config({})) == TrainConfig()


def test_values_from_the_config_file_section() -> None:
    cfg = load_config({"train": {"lr": 1, "optimizer": "adam", "shared_policy": True, "disseminate_every": 3}})
    tc = train_config(cfg)
    assert tc.lr == 1.0 and isinstance(tc.lr, float)
    assert tc.optimizer == "adam" and tc.shared_policy and tc.disseminate_every == 3


@pytest.mark.parametrize(
    ("train", "message"),
    [
        ({"bogus": 1}, "config key train.bogus: unknown key; allowed: algo, "),
        ({"workers": 0}, "train.workers: must be > 0, got 0"),
        ({"workers": 1.5}, "train.workers: expected an integer, got 1.5"),
        ({"gamma": 1.5}, "train.gamma: must be <= 1, got 1.5"),
        ({"lr": "fast"}, "train.lr: expected a number, got 'fast'"),
        ({"optimizer": "sgd"}, "train.optimizer: expected 'adam' or 'rmsprop', got 'sgd'"),
        ({"shared_policy": "yes"}, "train.shared_policy: expected true or false, got 'yes'"),
        ({"device": "tpu"}, "train.device: expected cpu, cuda or cuda:N, got 'tpu'"),
        ({"entropy_coef": -0.1}, "train.entropy_coef: must be >= 0, got -0.1"),
        ({"lr_final": -1}, "train.lr_final: must be >= 0, got -1"),
        ({"central_critic": True, "shared_policy": False},
         "train.central_critic: a central critic pools the AVs' features of one network: it needs shared_policy: true"),
    ],
)
def test_bad_keys_and_values_name_the_key(train: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)):
        load_config({"train": train})
    with pytest.raises(ConfigError, match=re.escape(message)):  # a raw section: the same check
        train_config(train)


def test_train_config_of_a_config_is_its_section() -> None:
    cfg = load_config({"train": {"algo": "ppo", "lr_final": 1e-5}})
    assert train_config(cfg) is cfg.train and cfg.train.algo == "ppo" and cfg.train.lr_final == 1e-5
    assert train_config({"algo": "ppo", "lr_final": "1e-5"}) == cfg.train  # YAML 1.1 reads 1e-5 as a string
    assert train_config(None) == TrainConfig()


def test_config_to_dict_round_trips_with_a_train_section() -> None:
    cfg = load_config({"train": {"lr": 0.001}, "reward": {"phi": 0.785}})
    again = load_config(cfg.to_dict())
    assert again == cfg
