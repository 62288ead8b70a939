"""TrainConfig validation: defaults, unknown keys and bad values name the key `train.<key>`."""

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
        ({"bogus": 1}, "train.bogus"),
        ({"workers": 0}, "train.workers"),
        ({"workers": 1.5}, "train.workers"),
        ({"gamma": 1.5}, "train.gamma"),
        ({"lr": "fast"}, "train.lr"),
        ({"optimizer": "sgd"}, "train.optimizer"),
        ({"shared_policy": "yes"}, "train.shared_policy"),
        ({"device": "tpu"}, "train.device"),
        ({"entropy_coef": -0.1}, "train.entropy_coef"),
    ],
)
def test_bad_keys_and_values_name_the_key(train: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        train_config(load_config({"train": train}))


def test_config_to_dict_round_trips_with_a_train_section() -> None:
    cfg = load_config({"train": {"lr": 0.001}, "reward": {"phi": 0.785}})
    again = load_config(cfg.to_dict())
    assert again == cfg
