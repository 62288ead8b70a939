"""The Conv3D actor-critic: shapes for both presets, dtype handling and the input's preparation, gradient flow, the
bfloat16 forward."""

import numpy as np
import pytest
import torch

from agents.model import ActorCritic, prepare
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


@pytest.mark.parametrize("bf16", [False, True])
@pytest.mark.parametrize("by_frame", [False, True])
def test_the_first_conv_gets_its_input_channels_last_in_the_forward_dtype(bf16: bool, by_frame: bool) -> None:
    # (B, F, C, H, W) uint8 in; the Conv3D sees (B, C, F, H, W) in `forward`, and each frame as a volume of depth 1
    # (K, C, 1, H, W) in `forward_frames` (its depth kernel is 1), scaled to [0, 1], laid out channels-last (oneDNN's
    # fast layout), in bfloat16 under the training's autocast (no second cast) and float32 without it.
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16, bf16=bf16)
    seen = []
    net.features.conv[0].register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    raw = torch.randint(0, 256, (3, 2, 4, 8, 16), dtype=torch.uint8)
    with torch.no_grad():
        if by_frame:
            net.forward_frames(raw.flatten(0, 1), torch.arange(6).view(3, 2))
        else:
            net(raw)
    (x,) = seen
    assert x.dtype == (torch.bfloat16 if bf16 else torch.float32)
    assert x.shape == ((6, 4, 1, 8, 16) if by_frame else (3, 4, 2, 8, 16))
    assert x.is_contiguous(memory_format=torch.channels_last_3d)
    expected = raw.permute(0, 2, 1, 3, 4).float() / 255.0
    if by_frame:
        x = x.squeeze(2).unflatten(0, (3, 2)).transpose(1, 2)
    torch.testing.assert_close(x.float(), expected, atol=0 if not bf16 else 4e-3, rtol=0 if not bf16 else 4e-3)


@pytest.mark.parametrize("shared", [True, False])
def test_distinct_frames_through_the_first_two_layers_once_give_the_conv3d_stacks_outputs_and_gradients(
        shared: bool) -> None:
    # Frames of stacks that shift by one per decision, given once each with where every observation's are (a
    # stack that began anew repeats its first frame); 5 frames, so the second layer's depths inside the stack and
    # at both of its padded ends are all there.
    torch.manual_seed(0)
    net = ActorCritic((5, 4, 16, 32), feature_dim=32, head_hidden=16, shared_encoder=shared, obs_norm=True)
    net.obs_norm.update(torch.rand(5, 4, 16, 32))
    frames = torch.rand(8, 4, 16, 32)
    index = torch.tensor([[0, 1, 2, 3, 4], [1, 2, 3, 4, 5], [2, 3, 4, 5, 6], [7, 7, 7, 7, 0]])
    whole = frames[index]  # (4, F, C, H, W)
    grads = []
    for path in (lambda: net.forward_frames(frames, index), lambda: net(whole)):
        net.zero_grad()
        logits, values = path()
        (logits.logsumexp(-1).sum() + logits[:, 1].sum() + values.square().sum()).backward()
        grads.append(((logits.detach(), values.detach()), {n: p.grad.clone() for n, p in net.named_parameters()}))
    (outputs, expected), reference = grads  # `forward` is Table 1's Conv3D stack on the whole observations
    for a, b in zip(outputs, reference[0], strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-5)
    for name, g in reference[1].items():
        assert g.abs().sum() > 0, name
        torch.testing.assert_close(expected[name], g, atol=1e-6, rtol=1e-4, msg=name)


def test_gradient_reaches_every_parameter() -> None:
    torch.manual_seed(0)
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16)
    logits, values = net(torch.rand(6, 2, 4, 8, 16))
    (logits.logsumexp(-1).sum() + logits[:, 1].sum() + values.sum()).backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name


@pytest.mark.parametrize("shared", [True, False])
def test_feature_norm_standardises_each_samples_features_in_every_encoder(shared: bool) -> None:
    torch.manual_seed(0)
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16, shared_encoder=shared, feature_norm=True)
    encoders = [net.features] if shared else [net.features, net.critic_features]
    x = torch.rand(6, 2, 4, 8, 16) * torch.arange(1, 7).view(6, 1, 1, 1, 1)  # samples of different scales
    for encoder in encoders:
        linear = encoder.fc[0](encoder.conv(prepare(x)))
        expected = torch.relu((linear - linear.mean(-1, keepdim=True))
                              / (linear.var(-1, correction=0, keepdim=True) + 1e-5).sqrt())
        torch.testing.assert_close(encoder(x), expected, atol=1e-5, rtol=1e-4)
    plain = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16, shared_encoder=shared)
    assert not any(isinstance(m, torch.nn.LayerNorm) for m in plain.modules())


@pytest.mark.parametrize("shared", [True, False])
def test_the_critics_loss_shapes_the_actors_features_only_through_a_shared_encoder(shared: bool) -> None:
    torch.manual_seed(0)
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16, shared_encoder=shared)
    assert net.shared_encoder is shared and (net.critic_features is None) is shared
    _, values = net(torch.rand(6, 2, 4, 8, 16))
    values.square().sum().backward()
    actor_encoder = [p.grad is not None and p.grad.abs().sum() > 0 for p in net.features.parameters()]
    assert all(actor_encoder) if shared else not any(actor_encoder)
    if not shared:
        assert all(p.grad.abs().sum() > 0 for p in net.critic_features.parameters())
        torch.testing.assert_close(net.value(torch.ones(2, 2, 4, 8, 16)), net(torch.ones(2, 2, 4, 8, 16))[1])


def test_a_central_critic_values_an_av_by_its_map_and_its_teams_while_the_actor_reads_its_own_alone() -> None:
    torch.manual_seed(0)
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16, central_critic=True)
    obs, teams = torch.rand(5, 2, 4, 8, 16), torch.tensor([7, 7, 3, 3, 3])
    with torch.no_grad():
        logits, values = net(obs, teams=teams)
        other = obs.clone()
        other[1] = torch.rand(2, 4, 8, 16)  # the scene of sample 0's teammate changes
        logits2, values2 = net(other, teams=teams)
        assert (values2[:2] - values[:2]).abs().min() > 1e-4
        torch.testing.assert_close(values2[2:], values[2:])  # another team's
        torch.testing.assert_close(logits2[[0, 2, 3, 4]], logits[[0, 2, 3, 4]])  # an actor reads its own map alone
        torch.testing.assert_close(net.value(obs, teams), values)
        alone, together = net(obs)[1], net(obs, teams=torch.zeros(5, dtype=torch.long))[1]
        torch.testing.assert_close(alone, net(obs, teams=torch.arange(5))[1])  # no teams: each AV alone
        assert (alone - together).abs().max() > 1e-4
        # The update's path, through each observation's frames, pools the same way.
        frames, index = obs.flatten(0, 1), torch.arange(10).view(5, 2)
        torch.testing.assert_close(net.forward_frames(frames, index, teams)[1], values, atol=1e-5, rtol=1e-5)


def test_obs_norm_keeps_each_pixels_running_mean_and_variance_over_batches() -> None:
    # Chan's merge of two batches equals the statistics of both at once, per channel and pixel; uint8 as [0, 1].
    net = ActorCritic((2, 3, 8, 16), feature_dim=32, head_hidden=16, obs_norm=True)
    gen = torch.Generator().manual_seed(0)
    a, b = (torch.randint(0, 256, (n, 3, 8, 16), dtype=torch.uint8, generator=gen) for n in (7, 4))
    net.obs_norm.update(a)
    net.obs_norm.update(b)
    both = torch.cat([a, b]).double() / 255
    assert float(net.obs_norm.count) == 11
    torch.testing.assert_close(net.obs_norm.mean.permute(2, 0, 1).double(), both.mean(0), atol=1e-6, rtol=0)
    torch.testing.assert_close(net.obs_norm.var.permute(2, 0, 1).double(), both.var(0, correction=0), atol=1e-6,
                               rtol=0)


@pytest.mark.parametrize("bf16", [False, True])
def test_obs_norm_standardises_the_first_convs_input_with_a_floor_and_a_clip(bf16: bool) -> None:
    net = ActorCritic((2, 2, 8, 16), feature_dim=32, head_hidden=16, bf16=bf16, obs_norm=True)
    seen = []
    net.features.conv[0].register_forward_pre_hook(lambda module, args: seen.append(args[0]))
    raw = torch.randint(0, 256, (3, 2, 2, 8, 16), dtype=torch.uint8)
    with torch.no_grad():
        net(raw)  # no statistics yet: scaled to [0, 1] only
        torch.testing.assert_close(seen[-1].float(), raw.permute(0, 2, 1, 3, 4).float() / 255, atol=4e-3, rtol=4e-3)
        # Channel 0 varies, channel 1 is constant (std 0, so the floor of 0.01 applies).
        frames = torch.stack([torch.tensor([[0.0] * 16] * 8), torch.full((8, 16), 0.5)]).expand(4, 2, 8, 16).clone()
        frames[:2, 0] = 1.0  # mean 0.5, std 0.5
        net.obs_norm.update(frames)
        x = torch.zeros(1, 2, 2, 8, 16)
        x[0, :, 0] = 1.0
        x[0, 0, 1, 0, 0] = 0.6  # (0.6 - 0.5) / 0.01 = 10, clipped to 5
        x[0, 1, 1, 0, 0] = 0.49
        given = x.clone()
        net(x)
    assert torch.equal(x, given)  # standardised in a copy, never in the caller's tensor
    got = seen[-1].float()  # (B, C, F, H, W)
    tol = {"atol": 0.04, "rtol": 0.01} if bf16 else {"atol": 1e-5, "rtol": 0}
    torch.testing.assert_close(got[0, 0], torch.ones(2, 8, 16), **tol)
    assert got[0, 1, 0, 0, 0] == 5.0 and abs(float(got[0, 1, 1, 0, 0]) + 1.0) < tol["atol"] + 1e-2
    assert got.is_contiguous(memory_format=torch.channels_last_3d)
    with torch.no_grad():  # the critic's value reads the same standardised input
        torch.testing.assert_close(net.value(x), net(x)[1], atol=1e-2 if bf16 else 1e-6, rtol=0)


@pytest.mark.parametrize("standardised", [False, True])
def test_the_input_prepared_chunk_by_chunk_is_the_input_prepared_whole(standardised: bool, monkeypatch) -> None:
    # Chunks of 3 samples over a batch of 10 (the last one short), against the whole batch as one chunk.
    net = ActorCritic((2, 3, 8, 16), feature_dim=32, head_hidden=16, obs_norm=True)
    gen = torch.Generator().manual_seed(1)
    obs = torch.randint(0, 256, (10, 2, 3, 8, 16), dtype=torch.uint8, generator=gen)
    if standardised:
        net.obs_norm.update(obs[:6, -1])
    norm = net.obs_norm if standardised else None
    whole = prepare(obs, norm)
    monkeypatch.setattr("agents.model.PREPARE_CHUNK_BYTES", 3 * 2 * 3 * 8 * 16 * 4)
    chunked = prepare(obs, norm)
    assert torch.equal(chunked, whole) and chunked.is_contiguous(memory_format=torch.channels_last_3d)
    reference = obs.permute(0, 2, 1, 3, 4).float() / 255  # (B, C, F, H, W) in [0, 1]
    if standardised:
        mean, std = (t.permute(2, 0, 1)[:, None] for t in (net.obs_norm.mean, net.obs_norm.var.sqrt()))
        reference = ((reference - mean) / std.clamp(min=0.01)).clamp(-5, 5)
    torch.testing.assert_close(chunked, reference, atol=1e-4, rtol=1e-5)


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



def float32_and_bf16() -> tuple[ActorCritic, ActorCritic]:
    """A small network and its twin (the same weights) whose forward runs in bfloat16 autocast."""
    torch.manual_seed(0)
    net = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16)
    twin = ActorCritic((2, 4, 8, 16), feature_dim=32, head_hidden=16, bf16=True)
    twin.load_state_dict(net.state_dict())
    return net, twin


def test_bfloat16_forward_keeps_float32_weights_and_outputs_close_to_float32() -> None:
    # bfloat16 rounds every layer's input to 8 significant bits (2^-9 relative); after the five layers of a
    # forward the outputs are about 1% of their scale off (measured), so 3% of the scale bounds it.
    net, twin = float32_and_bf16()
    obs = torch.rand(16, 2, 4, 8, 16)
    with torch.no_grad():
        (logits, values), (logits16, values16) = net(obs), twin(obs)
        only_values16 = twin.value(obs)
    assert logits16.dtype == values16.dtype == only_values16.dtype == torch.float32
    assert all(p.dtype == torch.float32 for p in twin.parameters())
    torch.testing.assert_close(logits16, logits, rtol=0, atol=0.03 * float(logits.abs().max()))
    torch.testing.assert_close(values16, values, rtol=0, atol=0.03 * float(values.abs().max()))
    torch.testing.assert_close(only_values16, values16)


def test_bfloat16_acting_takes_the_float32_greedy_actions_where_they_are_clear_cut() -> None:
    net, twin = float32_and_bf16()
    with torch.no_grad():
        for n in (net, twin):
            n.actor[-1].weight.mul_(1000)  # trained-like logits of order 1, not the initial 0.01 scale
    obs = np.random.default_rng(0).random((64, 2, 4, 8, 16), dtype=np.float32)
    with torch.no_grad():
        logits, _ = net(torch.from_numpy(obs))
    best = logits.topk(2, -1).values
    # Clear-cut: the best action leads the next by 10% of the logits' scale, 10 times bfloat16's error.
    clear = ((best[:, 0] - best[:, 1]) > 0.1 * logits.abs().max()).numpy()
    greedy = net.act(obs, greedy=True)
    assert clear.sum() >= 16 and len(set(greedy[clear])) > 1  # enough of them, and not all one action
    np.testing.assert_array_equal(twin.act(obs, greedy=True)[clear], greedy[clear])
