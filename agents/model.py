"""Actor-critic network of the paper's Table 1: a Conv3D feature extractor over stacked VelocityMaps.

Contract: `ActorCritic(obs_shape, n_actions)` takes observations shaped like the env's observation space,
`(B, F, C, H, W)` (F stacked frames, C channels), of dtype float32, float16 or uint8 (uint8 is scaled by
1/255), and returns action logits `(B, n_actions)` and state values `(B,)`, float32. With `bf16` the forward
runs in bfloat16 autocast: weights and outputs stay float32, the outputs off float32's by about 1% of their
scale, and not reproducible bit for bit run to run on CPUs with bfloat16 instructions. Frames are Conv3D's
depth axis and channels its channels. The flatten size follows from the observation shape by a dummy forward,
so the paper preset (10, 4, 64, 512) and the CPU default (5, 4, 32, 128) build from the same code. The actor
and the critic share the encoder, as the paper's network does, unless `shared_encoder=False`
(`train.shared_encoder`). With `obs_norm=True` (`train.obs_norm`) the input is standardised pixel by pixel first
(`ObsNorm`: running statistics the learner updates, saved with the weights), as SB3's `VecNormalize` does for
vector observations; without it, as in the paper, the input is only scaled to [0, 1]. With `feature_norm=True`
(`train.feature_norm`) the encoder normalises its features (LayerNorm between its FC layer and its ReLU). With
`central_critic=True` (`train.central_critic`) the critic reads, beside an AV's features, the mean of those of every AV
of its env at that decision (`teams`); the actor stays on the AV's own map, so acting needs no other AV's.
The first layer's depth kernel is 1 and the second's depth stride 1, so a frame's part in an observation's second
layer is the same wherever the frame stands in a stack (`frame_features`: its first-layer output convolved with each of
the second layer's depth taps): `forward_frames` takes observations as their distinct frames and where each
observation's are, and `FrameMemory` keeps the parts of frames already seen while acting.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from agents.losses import masked_logits
from cosim.errors import ConfigError


@dataclass(frozen=True)
class Conv3dSpec:
    channels: int
    kernel: tuple[int, int, int]  # (depth = frames, height, width)
    stride: tuple[int, int, int]
    padding: tuple[int, int, int]


# Table 1's kernels. Strides shrink the map; depth padding 1 on the 3-deep kernels keeps any F >= 1 valid,
# the last layer halves everything so the FC input stays moderate at the paper size (64*5*4*32 = 40960).
CONV_LAYERS: tuple[Conv3dSpec, ...] = (
    Conv3dSpec(32, (1, 8, 8), (1, 4, 4), (0, 2, 2)),
    Conv3dSpec(64, (3, 4, 4), (1, 2, 2), (1, 1, 1)),
    Conv3dSpec(64, (3, 3, 3), (2, 2, 2), (1, 1, 1)),
)


def _init(layer: nn.Module, gain: float) -> nn.Module:
    """Orthogonal weights, zero biases (the usual A2C/PPO initialisation)."""
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


class VelocityMapEncoder(nn.Module):
    """The feature extractor of Table 1: Conv3D x3 -> FC, `(B, F, C, H, W)` any dtype -> `(B, feature_dim)`.
    Also the features extractor of other libraries' policies (scripts/train_sb3.py)."""

    def __init__(self, obs_shape: tuple[int, ...], feature_dim: int = 512, layer_norm: bool = False) -> None:
        super().__init__()
        if len(obs_shape) != 4:
            raise ConfigError(f"observation shape must be (frames, channels, height, width), got {obs_shape}")
        frames, channels, height, width = (int(s) for s in obs_shape)
        relu_gain = math.sqrt(2.0)
        layers: list[nn.Module] = []
        in_ch = channels
        for spec in CONV_LAYERS:
            layers += [_init(nn.Conv3d(in_ch, spec.channels, spec.kernel, spec.stride, spec.padding), relu_gain),
                       nn.ReLU()]
            in_ch = spec.channels
        self.conv = nn.Sequential(*layers, nn.Flatten())
        with torch.no_grad():  # the flatten size follows from the observation shape
            try:
                n_flat = self.conv(torch.zeros(1, channels, frames, height, width)).shape[1]
            except RuntimeError as exc:
                raise ConfigError(f"observation: shape {obs_shape} is too small for the paper's Conv3D stack; raise "
                                  f"observation.height_px / width_px / frames ({exc})") from None
        norm = [nn.LayerNorm(feature_dim)] if layer_norm else []
        self.fc = nn.Sequential(_init(nn.Linear(n_flat, feature_dim), relu_gain), *norm, nn.ReLU())
        self.conv.to(memory_format=torch.channels_last_3d)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.encode(prepare(obs))

    def encode(self, x: torch.Tensor) -> torch.Tensor:
        """`prepare`'s output -> (B, feature_dim)."""
        return self.fc(self.conv(x))

    def frame_features(self, x: torch.Tensor) -> torch.Tensor:
        """`prepare`'s output of single frames (K, C, 1, H, W) -> each frame's part in the second layer: its first-layer
        output (Conv3D and ReLU) convolved with each of the second Conv3D's depth taps, (K, kd, h2, w2, c2) (`taps`).
        The second layer's output at depth d of a stack is the sum over taps k of tap k of the stack's frame d - pd + k
        (pd its depth padding), plus its bias (`encode_frames`): a frame that several observations share (a stack
        shifts by one frame per decision) goes through the first two layers once, a fifth of their work per sample."""
        return self.taps(self.conv[1](self.conv[0](x)).squeeze(2))

    def taps(self, y: torch.Tensor) -> torch.Tensor:
        """First-layer outputs of single frames (K, c1, h1, w1) -> their 2D convolution with each depth tap of the
        second Conv3D (its depth stride is 1), (K, kd, h2, w2, c2): one Conv2D with kd x c2 output channels."""
        conv = self.conv[2]
        kd, c2 = conv.kernel_size[0], conv.out_channels
        weight = conv.weight.permute(2, 0, 1, 3, 4).reshape(kd * c2, conv.in_channels, *conv.kernel_size[1:])
        out = nn.functional.conv2d(y, weight, None, conv.stride[1:], conv.padding[1:])  # (K, kd * c2, h2, w2)
        return out.unflatten(1, (kd, c2)).permute(0, 1, 3, 4, 2).contiguous()

    def encode_frames(self, features: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Distinct frames' `frame_features` (K, kd, h2, w2, c2) and, for each of B observations, where its frames
        are in them, oldest to newest (B, F) -> (B, feature_dim), as `encode` of the observations gives."""
        conv = self.conv[2]
        kd, pd = conv.kernel_size[0], conv.padding[0]
        b, f = index.shape
        # Each (observation, depth)'s output sums the taps of the frames under its kernel; the depth padding's zero
        # frames add nothing, so they are left out of its sum (bags of fewer rows at the stack's ends).
        window = nn.functional.pad(index, (pd, kd - 1 - pd), value=-1).unfold(1, kd, 1)  # (B, F, kd)
        inside = window >= 0
        rows = (window * kd + torch.arange(kd, device=index.device))[inside]
        counts = inside.sum(-1).flatten()
        offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)[:-1]])
        flat = features.flatten(2)
        out = nn.functional.embedding_bag(rows, flat.reshape(-1, flat.shape[2]), offsets, mode="sum")
        # The bias in the sums' dtype: a float32 bias would promote a bfloat16 forward's tensors to float32 here.
        y = torch.relu(out.view(b, f, *features.shape[2:]) + conv.bias.to(out.dtype)).permute(0, 4, 1, 2, 3)
        for layer in itertools.islice(self.conv, 4, None):
            y = layer(y)
        return self.fc(y)


# Bytes of the encoder's input prepared at once on the CPU (`prepare`): a chunk that stays in a core's L2 cache.
PREPARE_CHUNK_BYTES = 1 << 20


def prepare(obs: torch.Tensor, norm: ObsNorm | None = None) -> torch.Tensor:
    """(B, F, C, H, W) observations of any dtype -> the encoder's input (B, C, F, H, W): channels as Conv3D
    channels, frames as depth, in [0, 1] (uint8 scaled by 1/255), then standardised by `norm` where given."""
    # Channels-last: oneDNN's Conv3D on the CPU runs about twice as fast in this layout. One copy makes the type
    # and the layout, the scale (and the standardisation) in place: the input's preparation was about half of a
    # small batch's forward in three copies. The copy walks the input in the order it writes (B, F, H, W, C),
    # about twice as fast as gathering into channels_last_3d directly, and writes the dtype autocast would cast it
    # to (bfloat16 in training: half the bytes, and no second copy by autocast).
    device = obs.device.type
    dtype = torch.get_autocast_dtype(device) if torch.is_autocast_enabled(device) else torch.float32
    b, f, c, h, w = obs.shape
    x = torch.empty((b, f, h, w, c), dtype=dtype, device=obs.device)
    src = obs.permute(0, 1, 3, 4, 2)
    raw = obs.dtype == torch.uint8
    # Until the statistics have taken in a batch the input is only scaled.
    coefficients = norm.coefficients(1 / 255.0 if raw else 1.0, dtype) if norm is not None and norm.count else None
    # On the CPU chunk by chunk, each copied, scaled and clipped while it is in the core's cache: in passes over the
    # whole batch, each larger than the cache, the standardised preparation of an update's minibatch (141 samples)
    # took 2.1 times as long (33 against 15 ms on one thread, 15 against 7 on two; Intel Xeon, bfloat16).
    step = max(1, PREPARE_CHUNK_BYTES // (f * h * w * c * x.element_size())) if device == "cpu" else max(b, 1)
    for start in range(0, b, step):
        part = x[start:start + step]
        part.copy_(src[start:start + step])
        if coefficients is not None:
            torch.addcmul(coefficients[1], part, coefficients[0], out=part)
            part.clamp_(-norm.clip, norm.clip)
        elif raw:
            part.div_(255.0)
    return x.permute(0, 4, 1, 2, 3)


class ObsNorm(nn.Module):
    """Running mean and variance of each pixel of each channel (frames pooled: a stack holds the same frames,
    shifted), the encoder's input standardised by them: (x - mean) / max(std, `min_std`), clipped to +-`clip`.

    Why: on the default scenario 93% of the input's values are 0 and nine in ten of the rest are road, the same
    in most scenes, so at the paper's initialisation the encoder's features barely vary from scene to scene (their
    spread across scenes a third of their size, 31-32% of its units off in every scene) and the policy starts out
    blind to them; standardised, the spread is nine tenths of the size and 5-8% of the units are off everywhere
    (scripts/probe_features.py, docs/results.md). The floor on the std keeps a pixel that has rarely held a vehicle
    from turning one into a spike, the clip bounds the rest. `update(frames)` takes in a batch (the learner calls it
    after each update, with the newest frame of every sample the update trained on, so that a batch is acted on and
    trained on under the same statistics); until the first, the input is only scaled to [0, 1]."""

    def __init__(self, channels: int, height: int, width: int, *, min_std: float = 0.01, clip: float = 5.0) -> None:
        super().__init__()
        self.min_std, self.clip = min_std, clip
        # (H, W, C): the layout `prepare` standardises in.
        self.register_buffer("count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("mean", torch.zeros(height, width, channels))
        self.register_buffer("var", torch.ones(height, width, channels))

    @torch.no_grad()
    def update(self, frames: torch.Tensor) -> None:
        """Take in frames (N, C, H, W) of the observation's dtype (uint8 in [0, 255], else in [0, 1]), merged
        with the statistics so far as Chan et al.'s parallel algorithm does (SB3's `RunningMeanStd`)."""
        n = frames.shape[0]
        if n == 0:
            return
        # Two passes in place over one float copy, (N, H * W * C) in the layout the frames are stored in:
        # torch.var_mean over the first dimension of the permuted frames took about three times as long.
        x = frames.permute(0, 2, 3, 1).reshape(n, -1).to(self.mean.device, torch.float32, copy=True)
        if frames.dtype == torch.uint8:
            x.div_(255.0)
        batch_mean = x.mean(0)
        batch_var = x.sub_(batch_mean).square_().mean(0)
        batch_mean, batch_var = batch_mean.view_as(self.mean), batch_var.view_as(self.var)
        seen = float(self.count)
        total = seen + n
        delta = batch_mean - self.mean
        self.var.copy_((self.var * seen + batch_var * n + delta.square() * (seen * n / total)) / total)
        self.mean.add_(delta * (n / total))
        self.count.fill_(total)

    def coefficients(self, unit: float, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
        """(scale, shift), (H, W, C) in `dtype`: x * scale + shift standardises x (B, F, H, W, C), whose values
        times `unit` are in [0, 1] (the clip to +-`clip` follows); after the first `update`."""
        # One multiply-add in x's own dtype, the scale folded in: subtracting and dividing in place with float32
        # statistics on a bfloat16 input took about six times as long as the plain preparation (mixed-dtype loops).
        inv = self.var.sqrt().clamp(min=self.min_std).reciprocal()
        return (inv * unit).to(dtype), (-self.mean * inv).to(dtype)


class ActorCritic(nn.Module):
    """Feature extractor (`VelocityMapEncoder`) under an actor head (logits) and a critic head (value); with
    `shared_encoder=False` the critic has an encoder of its own (`critic_features`); with `obs_norm=True` both
    read the input standardised by `obs_norm` (an `ObsNorm`, else None); with `feature_norm=True` each encoder
    normalises its features; with `central_critic=True` the critic also reads its team's mean features."""

    def __init__(self, obs_shape: tuple[int, ...], n_actions: int = 5, *, feature_dim: int = 512,
                 head_hidden: int = 256, bf16: bool = False, shared_encoder: bool = True,
                 obs_norm: bool = False, feature_norm: bool = False, central_critic: bool = False) -> None:
        super().__init__()
        # Run the forward pass in bfloat16 (weights and outputs stay float32): about twice as fast on CPUs with
        # AMX / AVX512-BF16 (scripts/bench_train.py); the trainer turns it on there, evaluation never does.
        self.bf16 = bf16
        self.obs_shape = tuple(int(s) for s in obs_shape)
        self.n_actions = n_actions
        relu_gain = math.sqrt(2.0)
        self.features = VelocityMapEncoder(self.obs_shape, feature_dim, feature_norm)
        # Separate: the critic's regression no longer shapes the actor's features (MAPPO's default; Andrychowicz et
        # al. 2021 found shared ones worse), at twice the encoder's work per sample.
        self.critic_features = None if shared_encoder else VelocityMapEncoder(self.obs_shape, feature_dim,
                                                                              feature_norm)
        self.obs_norm = ObsNorm(*self.obs_shape[1:]) if obs_norm else None
        self.actor = nn.Sequential(_init(nn.Linear(feature_dim, head_hidden), relu_gain), nn.ReLU(),
                                   _init(nn.Linear(head_hidden, n_actions), 0.01))
        # A centralised critic (MAPPO's; Lowe et al. 2017's centralised training) reads its own features beside the
        # mean of its team's: the SVO reward's social part is the others' utility, the merging vehicle's included,
        # which the AVs around it see and this one may not.
        self.central_critic = central_critic
        self.critic = nn.Sequential(_init(nn.Linear(feature_dim * (2 if central_critic else 1), head_hidden),
                                          relu_gain), nn.ReLU(), _init(nn.Linear(head_hidden, 1), 1.0))

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any) -> None:
        # Checkpoints written before the encoder was a module of its own name its layers conv.* and fc.*.
        for key in [k for k in state_dict if k.startswith((prefix + "conv.", prefix + "fc."))]:
            state_dict[prefix + "features." + key[len(prefix):]] = state_dict.pop(key)
        super()._load_from_state_dict(state_dict, prefix, *args)

    def _precision(self, obs: torch.Tensor, float32: bool = False) -> torch.autocast:
        return torch.autocast(obs.device.type, dtype=torch.bfloat16, enabled=self.bf16 and not float32)

    def forward(self, obs: torch.Tensor, float32: bool = False,
                teams: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """(B, F, C, H, W) -> logits (B, A), values (B,), float32; `float32`: without bfloat16 autocast even where
        the network trains with it (validation plays as evaluation does); `teams` (B,): for a central critic, the
        observations that are of one env at one decision share a number (None: each its own; `_critic_input`).
        Through Table 1's Conv3D stack itself, the fastest way for observations that share no frames
        (scripts/bench_frames.py)."""
        with self._precision(obs, float32):
            x = prepare(obs, self.obs_norm)
            h = self.features.encode(x)
            return self._outputs(h, h if self.critic_features is None else self.critic_features.encode(x), teams)

    def forward_frames(self, frames: torch.Tensor, index: torch.Tensor,
                       teams: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """`forward` of B observations given as their distinct frames (K, C, H, W) and, for each observation, where
        its frames are in them, oldest to newest (B, F): the first two layers' work is once per distinct frame."""
        with self._precision(frames):
            return self.from_features(self.frame_features(frames), index, teams)

    def frame_features(self, frames: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Frames (K, C, H, W) of any dtype the observations have -> each one's part in the second layer (K, kd, h2,
        w2, c2) in every encoder (the actor's, then the critic's where it has its own;
        `VelocityMapEncoder.frame_features`), in the dtype of the forward's precision where called in it."""
        x = prepare(frames.unsqueeze(1), self.obs_norm)
        return tuple(encoder.frame_features(x) for encoder in self._encoders())

    def from_features(self, features: tuple[torch.Tensor, ...], index: torch.Tensor,
                      teams: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Every encoder's `frame_features` of distinct frames and where each of B observations' frames are in them
        (B, F) -> logits (B, A), values (B,), float32."""
        h = self.features.encode_frames(features[0], index)
        return self._outputs(h, h if self.critic_features is None else
                             self.critic_features.encode_frames(features[1], index), teams)

    def _outputs(self, h: torch.Tensor, critic_h: torch.Tensor,
                 teams: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        return self.actor(h).float(), self.critic(self._critic_input(critic_h, teams)).squeeze(-1).float()

    def _critic_input(self, h: torch.Tensor, teams: torch.Tensor | None) -> torch.Tensor:
        """The critic's features (B, D), or with a central critic each observation's beside the mean of its team's
        (B, 2D): the observations whose `teams` (B,) number is the same (None: each alone)."""
        if not self.central_critic:
            return h
        if teams is None:
            return torch.cat([h, h], 1)
        ids, inverse = teams.to(h.device).unique(return_inverse=True)
        sums = h.new_zeros((len(ids), h.shape[1])).index_add_(0, inverse, h)
        counts = torch.bincount(inverse, minlength=len(ids)).to(h.dtype)
        return torch.cat([h, (sums / counts[:, None]).index_select(0, inverse)], 1)

    def _encoders(self) -> tuple[VelocityMapEncoder, ...]:
        return (self.features,) if self.critic_features is None else (self.features, self.critic_features)

    @property
    def shared_encoder(self) -> bool:
        return self.critic_features is None

    def value(self, obs: torch.Tensor, teams: torch.Tensor | None = None) -> torch.Tensor:
        """(B, F, C, H, W) -> (B,), float32: the critic's encoder alone (`teams` as in `forward`)."""
        encoder = self.features if self.critic_features is None else self.critic_features
        with self._precision(obs):
            h = encoder.encode(prepare(obs, self.obs_norm))
            return self.critic(self._critic_input(h, teams)).squeeze(-1).float()

    @torch.no_grad()
    def act(self, obs: np.ndarray | torch.Tensor, greedy: bool = False,
            mask: np.ndarray | torch.Tensor | None = None) -> np.ndarray:
        """Actions (B,) int64 for an observation batch (B, F, C, H, W): argmax if greedy, else sampled; with `mask`
        (B, A; 0 = not allowed) among the allowed actions only."""
        device = next(self.parameters()).device
        if isinstance(obs, np.ndarray):
            obs = torch.from_numpy(obs if obs.flags.writeable else obs.copy())  # env views are read-only
        logits, _ = self(obs.to(device))
        logits = masked_logits(logits, None if mask is None else torch.as_tensor(mask))
        if greedy:
            return logits.argmax(-1).cpu().numpy()
        return torch.distributions.Categorical(logits=logits).sample().cpu().numpy()


class FrameMemory:
    """For a network whose weights stay as they are (the learner's acting through one collection), the frame features
    (`ActorCritic.frame_features`) of each slot's last F frames (a slot: one agent of one worker), per encoder, in a
    ring per slot: an observation that continues its slot's last one (its stack shifted by a frame:
    `agents.multiagent.Batch.continues`) runs the first two layers on its newest frame only, which takes the place of
    the slot's oldest, and reads the others where they are (`__call__`)."""

    def __init__(self, net: ActorCritic) -> None:
        self.net = net
        self.rings: tuple[torch.Tensor, ...] = ()  # per encoder (slots * F, kd, h2, w2, c2): slot s's at s * F ...
        self.newest = torch.zeros(0, dtype=torch.long)  # (slots,) where in its ring each slot's newest frame is

    def __call__(self, obs: torch.Tensor, slots: torch.Tensor, continues: torch.Tensor,
                 teams: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """`net(obs, teams=teams)` for observations (B, F, C, H, W) of distinct slots (B,), of which those `continues`
        (B,) flags continue the slot's last one; every slot's ring then holds these observations' frames."""
        f = obs.shape[1]
        on, anew = continues.nonzero().squeeze(1), (~continues).nonzero().squeeze(1)
        ids = torch.cat([on * f + f - 1, (anew[:, None] * f + torch.arange(f, device=obs.device)).flatten()])
        # Selected channels last, the layout the learner's observations are stored in (agents.multiagent.Batch): one
        # row copy per frame, where a selection in the (C, H, W) view transposes every frame.
        frames = obs.flatten(0, 1).permute(0, 2, 3, 1).index_select(0, ids).permute(0, 3, 1, 2)
        self._grow(int(slots.max()) + 1, obs.device)
        newest = self.newest.index_select(0, slots)
        newest[on] = (newest[on] + 1) % f
        newest[anew] = f - 1
        self.newest.index_copy_(0, slots, newest)
        at = torch.cat([slots[on] * f + newest[on],
                        (slots[anew, None] * f + torch.arange(f, device=obs.device)).flatten()])
        with self.net._precision(obs):
            features = self.net.frame_features(frames)
            rows = len(self.newest) * f
            self.rings = tuple(_padded(self.rings[k] if self.rings else x.new_zeros((0, *x.shape[1:])), rows)
                               for k, x in enumerate(features))
            for ring, x in zip(self.rings, features, strict=True):
                ring.index_copy_(0, at, x)
            # Oldest to newest: the ring from the place after the newest frame on.
            index = slots[:, None] * f + (newest[:, None] + 1 + torch.arange(f, device=obs.device)) % f
            return self.net.from_features(self.rings, index, teams)

    def _grow(self, slots: int, device: torch.device) -> None:
        """Room for `slots` slots (one acted on for the first time has no frames to reuse)."""
        self.newest = _padded(self.newest.to(device), slots)


def _padded(x: torch.Tensor, rows: int) -> torch.Tensor:
    """`x` with zero rows appended up to `rows` rows (itself where it has them)."""
    return x if x.shape[0] >= rows else torch.cat([x, x.new_zeros((rows - x.shape[0], *x.shape[1:]))])


# Relative L2 error of one layer's bfloat16 gradient against float32's beyond which it is wrong, not rounded:
# bfloat16 keeps 8 significant bits, and a sound kernel lands within about 0.3% (measured per layer).
BF16_GRADIENT_TOL = 0.05


def bf16_gradient_error(obs_shape: tuple[int, ...], n_actions: int, feature_dim: int, head_hidden: int,
                        device: torch.device | str = "cpu") -> tuple[str, float]:
    """The gradient (of a layer's weight, bias or input) that bfloat16 autocast gets furthest from float32's on
    this machine, layer by layer at this network's shapes, and that relative L2 error (inf if not finite).

    Why: on CPUs with AVX512-BF16, torch 2.13's oneDNN Conv3D gives wrong weight gradients in bfloat16 for some
    shapes (2 frames, or 3 on small maps: off by 100% to 1e36, sometimes NaN), while the presets' shapes are
    within 0.3%. Each layer is checked alone, on the input a float32 forward gives it: through the whole
    network, rounding that cancels makes sound gradients differ by up to 50% too. The global RNG is left as
    it was, so a run stays reproducible."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)
        net = ActorCritic(obs_shape, n_actions, feature_dim=feature_dim, head_hidden=head_hidden).to(device)
        # Each convolution and linear kernel as training runs it, with the module whose weight (and bias) it trains:
        # the second Conv3D runs as its depth taps (a Conv2D, `VelocityMapEncoder.taps`), on the first layer's output
        # of single frames; the taps' sums and its bias (`encode_frames`) are plain sums, not checked.
        kernels: dict[str, tuple[Any, nn.Module]] = {
            name: (m, m) for name, m in net.named_modules()
            if isinstance(m, nn.Conv3d | nn.Linear) and not name.endswith("conv.2")}
        inputs: dict[str, torch.Tensor] = {}
        hooks = [m.register_forward_hook(lambda m, i, o, name=name: inputs.__setitem__(name, i[0].detach()))
                 for name, (m, _) in kernels.items()]
        for name, m in net.named_modules():
            if isinstance(m, VelocityMapEncoder):
                taps = f"{name}.conv.2 (depth taps)"
                kernels[taps] = (m.taps, m.conv[2])
                hooks.append(m.conv[1].register_forward_hook(
                    lambda m, i, o, name=taps: inputs.__setitem__(name, o.detach().squeeze(2))))
        with torch.no_grad():  # as the update runs the network: frame by frame
            frames = obs_shape[0]
            net.forward_frames(torch.rand((2 * frames, *obs_shape[1:]), device=device),
                               torch.arange(2 * frames, device=device).view(2, frames))
        for hook in hooks:
            hook.remove()
        # Positive upstream gradients on non-negative inputs (observations, ReLU outputs): the weight and bias
        # gradients are sums without cancellation, so rounding stays relative to them.
        upstream = {name: 0.5 + torch.rand_like(fn(inputs[name])) for name, (fn, _) in kernels.items()}
    worst, largest = "", 0.0
    for name, (fn, layer) in kernels.items():
        grads = []
        for bf16 in (False, True):
            x = inputs[name].clone().requires_grad_(True)
            layer.zero_grad()
            with torch.autocast(x.device.type, dtype=torch.bfloat16, enabled=bf16):
                out = fn(x)
            (out.float() * upstream[name]).sum().backward()
            parts = {"weight": layer.weight.grad, "bias": layer.bias.grad, "input": x.grad}
            grads.append({part: grad for part, grad in parts.items() if grad is not None})
        for part, ref in grads[0].items():
            got = grads[1][part].double()
            ref = ref.double()
            err = float((got - ref).norm() / ref.norm()) if torch.isfinite(got).all() and ref.norm() > 0 else (
                0.0 if torch.equal(got, ref) else math.inf)
            if err > largest or not worst:
                worst, largest = f"{name}.{part}" if part != "input" else f"{name} (input)", err
    return worst, largest
