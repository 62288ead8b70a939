"""The Conv3D actor-critic: shapes for both presets, dtype handling, gradient flow."""

import numpy as np
import pytest
import torch

from agents.model import ActorCritic
from cosim.config import OBSERVATION_PRESETS
from cosim.errors import ConfigError


def preset_shape(name: str) -> tuple[int, int, int, int]:
    p = OBSERVATION_PRESETS[name]
    return (p["frames"], 4, p["height_px"], p["width_px"])


def test_default_preset_shapes() -> None:
    net = ActorCritic(preset_shape("default"))
    logits, values = net(torch.rand(3, *preset_shape("default")))
    assert logits.shape == (3, 5) and values.shape == (3,)


def test_paper_preset_one_forward() -> None:
    torch.manual_seed(0)
    net = ActorCritic(preset_shape("paper"))
    with torch.no_grad():
        logits, values = net(torch.rand(1, *preset_shape("paper")))
    assert logits.shape == (1, 5) and values.shape == (1,)


def test_uint8_is_scaled_like_float() -> None:
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16)
    raw = torch.randint(0, 256, (4, 2, 4, 8, 16), dtype=torch.uint8)
    with torch.no_grad():
        a, va = net(raw)
        b, vb = net(raw.float() / 255.0)
        c, _ = net((raw.float() / 255.0).half())
    torch.testing.assert_close(a, b)
    torch.testing.assert_close(va, vb)
    torch.testing.assert_close(a, c, atol=1e-3, rtol=1e-3)


def test_gradient_reaches_every_parameter() -> None:
    torch.manual_seed(0)
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16)
    logits, values = net(torch.rand(6, 2, 4, 8, 16))
    (logits.logsumexp(-1).sum() + logits[:, 1].sum() + values.sum()).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


def test_act_on_read_only_numpy_views() -> None:
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16)
    obs = np.random.default_rng(0).random((5, 2, 4, 8, 16), dtype=np.float32)
    obs.flags.writeable = False
    greedy = net.act(obs, greedy=True)
    assert greedy.shape == (5,) and greedy.dtype == np.int64
    np.testing.assert_array_equal(greedy, net.act(obs, greedy=True))
    assert set(net.act(obs).tolist()) <= set(range(5))


def test_too_small_observation_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="too small"):
        ActorCritic((1, 4, 2, 2))


def test_weights_saved_before_the_encoder_module_still_load() -> None:
    # Checkpoints of earlier versions name the encoder's layers conv.* / fc.* (no "features." prefix).
    torch.manual_seed(0)
    saved = ActorCritic((5, 4, 32, 128), feature_dim=32, head_hidden=16)
    old_names = {k.removeprefix("features."): v for k, v in saved.state_dict().items()}
    assert "conv.0.weight" in old_names
    net = ActorCritic((5, 4, 32, 128), feature_dim=32, head_hidden=16)
    net.load_state_dict(old_names)
    assert all(torch.equal(v, net.state_dict()[k]) for k, v in saved.state_dict().items())
