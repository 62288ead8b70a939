"""Checkpoints of a training run: atomic writes, validation on load, and policies for evaluation.

Contract:
- `save_checkpoint(path, payload)` writes via a temp file in the same folder and `os.replace`, so a
  crash mid-write leaves the previous checkpoint intact; beside it goes `policy.pt`, the trained networks (their
  weights' moving averages with `train.policy_ema`: `played_nets`) with their spec, counters and config but
  without optimizer, acting copies or RNG states: a few MB for
  evaluation and sharing, where the resumable checkpoint is several times that. Both are written in full
  before either is replaced; a failed write (a full disk) is a `CheckpointError` naming the file and the
  reason, with the previous pair left as it was.
- `read_checkpoint(path, expect=...)` returns the payload, or raises `CheckpointError` (a
  `cosim.errors.CosimError`) naming the file when it is missing, unreadable, not ours, or incompatible
  with the expected obs shape / dtype / number of agents / policy layout.
- `save_policy(path, payload, **extra)` writes the policy file of a payload alone (`best.pt`: the policy that did
  best in validation, with its figures as `validation`).
- `export_policy(src, dst)` writes a run's networks as a policy file in float16 (a shipped policy, a run's
  progress committed between sessions).
- `load_policy(path)` (a run folder, its `policy.pt` or `best.pt`, or a checkpoint) returns `(policies, meta)`:
  `policies` maps each agent name to its trained `ActorCritic` (eval mode; the same object for every agent when the
  policy is shared), whose `act(obs (B, F, C, H, W), greedy)` gives actions; `meta` holds the checkpoint's
  spec, counters, config and, for `best.pt`, its validation figures.
  `act_agents(policies, obs, greedy, masks)` acts for named agents, one forward per network (agents sharing a
  network are batched), the way evaluation plays a checkpoint; with `masks` (agent -> the env's action mask)
  among the allowed actions only. `TrainedPolicy` masks with the env's `action_masks()` (what its infos carry)
  when the run trained with `train.action_mask` (its checkpoint's train section; runs from before the key
  existed trained without).
Payload layout (format "cosim-ma-a2c", version 2): spec {agents, obs_shape, obs_dtype, n_actions,
shared_policy, feature_dim, head_hidden, shared_encoder, obs_norm, feature_norm and central_critic (absent before
they existed: shared, off, off, off)}, policy
(MultiAgentPolicy.state_dict()), counters (with train_s), rng {python, numpy, torch}, train (TrainConfig as a dict),
config (Config.to_dict()), phis (each AV's SVO [rad]). The policy file ("cosim-policy", same version): spec, nets,
counters, train, config, phis.
"""

from __future__ import annotations

import json
import random
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from pettingzoo import ParallelEnv

from agents.model import ActorCritic
from agents.validation import describe
from cosim.errors import CosimError
from cosim.files import atomic_path, file_sha256

FORMAT, VERSION = "cosim-ma-a2c", 2
POLICY_FORMAT = "cosim-policy"
CHECKPOINT_NAME = "checkpoint.pt"  # everything a resume needs
NET_RECORD = "net.json"  # the net a run trains on (path, sha256, summary) and the scenario resolved on it
POLICY_NAME = "policy.pt"  # the trained networks alone, for evaluation and sharing
BEST_NAME = "best.pt"  # a policy file: the networks that did best in validation (agents.validation)


class CheckpointError(CosimError):
    """A checkpoint is missing, corrupt, or does not fit the current env / config."""


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    """The resumable checkpoint at `path` and the policy-only file beside it (`POLICY_NAME`), both written in
    full before either replaces its old one, so that they stay a pair; `CheckpointError` naming the file when a
    write fails (a full disk), the previous pair left as it was."""
    small = policy_payload(payload)
    try:
        with atomic_path(path) as tmp, atomic_path(path.with_name(POLICY_NAME)) as small_tmp:
            _save({"format": FORMAT, "version": VERSION, **payload}, tmp)
            _save(small, small_tmp)
    except OSError as exc:
        kept = (f"the previous checkpoint ({path.name}, {POLICY_NAME}) is unchanged" if path.is_file()
                else "no checkpoint was written")
        raise CheckpointError(f"checkpoint {exc.filename or path}: cannot write it ({exc.strerror or exc}); "
                              f"{kept}") from None


def played_nets(policy: Mapping[str, Any]) -> list[dict[str, Any]]:
    """The networks of a `MultiAgentPolicy.state_dict()` that a policy file holds: each network's averaged copy where
    the run keeps one (`train.policy_ema`) and it has begun, else the trained network."""
    averaged, counts = policy.get("averaged") or [], policy.get("averaged_counts") or []
    if not averaged:
        return policy["nets"]
    return [avg if n else net for net, avg, n in zip(policy["nets"], averaged, counts, strict=True)]


def policy_payload(payload: dict[str, Any], **extra: Any) -> dict[str, Any]:
    """The policy file's content (module doc) of a checkpoint payload, with `extra` entries."""
    return {"format": POLICY_FORMAT, "version": VERSION, "nets": played_nets(payload["policy"]),
            **{k: payload[k] for k in ("spec", "counters", "train", "config", "phis") if k in payload}, **extra}


def save_policy(path: Path, payload: dict[str, Any], **extra: Any) -> None:
    """The policy file of a checkpoint payload alone (`best.pt`), written atomically; `CheckpointError` naming the
    file when the write fails, the previous file left as it was."""
    try:
        with atomic_path(path) as tmp:
            _save(policy_payload(payload, **extra), tmp)
    except OSError as exc:
        raise CheckpointError(f"policy file {exc.filename or path}: cannot write it ({exc.strerror or exc}); the "
                              f"previous one is unchanged") from None


def export_policy(src: Path, dst: Path, dtype: torch.dtype = torch.float16, **changed: Any) -> None:
    """A policy file (`policy.pt`, `best.pt`) or checkpoint's networks as a policy file at `dst` with its weights in
    `dtype` (float16: half the size, for a repository; `load_policy` loads them into float32 networks), written
    atomically; the spec, counters, config and validation figures go along, those named in `changed` (a run joined
    onto the snapshot it continues: its counters) replaced."""
    payload = torch.load(src, map_location="cpu", weights_only=True)
    if payload.get("format") == FORMAT:
        payload = policy_payload(payload)
    elif payload.get("format") != POLICY_FORMAT:
        raise CheckpointError(f"{src}: neither a {POLICY_FORMAT} file nor a {FORMAT} checkpoint")
    # The input's running statistics (ObsNorm: a few kB) stay as they are: float16 would turn a long run's sample
    # count into inf, and the standardisation the weights learned under would drift.
    nets = [{k: v.to(dtype) if v.is_floating_point() and not k.startswith("obs_norm.") else v for k, v in sd.items()}
            for sd in payload["nets"]]
    with atomic_path(dst) as tmp:
        _save({**payload, **changed, "nets": nets, "dtype": str(dtype).removeprefix("torch.")}, tmp)


def _save(obj: Any, path: Path) -> None:
    """`torch.save` into `path`; a failed write (a full disk) is an OSError naming `path`."""
    # Through a file of ours: a failed write is then the context of the RuntimeError that torch's zip writer
    # raises (given a path, torch leaves only "iostream error"), and it comes out as the OSError it is.
    try:
        with open(path, "wb") as f:
            torch.save(obj, f)
    except RuntimeError as exc:
        cause = exc.__context__
        while cause is not None and not isinstance(cause, OSError):
            cause = cause.__context__
        if cause is None:
            raise
        raise OSError(cause.errno, cause.strerror or str(cause), str(path)) from None
    except OSError as exc:  # the last buffered bytes, written at close
        raise OSError(exc.errno, exc.strerror or str(exc), exc.filename or str(path)) from None


def read_checkpoint(path: Path, expect: dict[str, Any] | None = None) -> dict[str, Any]:
    """Load and check a checkpoint; `expect` are spec entries that must match (e.g. obs_shape)."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: not found")
    return _checked_checkpoint(_load(path), path, expect)


def _load(path: Path) -> Any:
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise CheckpointError(f"checkpoint {path}: corrupt or not a checkpoint ({type(exc).__name__}: "
                              f"{str(exc).splitlines()[0] if str(exc) else ''})") from None


def _checked_checkpoint(payload: Any, path: Path, expect: dict[str, Any] | None = None) -> dict[str, Any]:
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"checkpoint {path}: not a {FORMAT} checkpoint")
    if payload.get("version") != VERSION:
        raise CheckpointError(f"checkpoint {path}: version {payload.get('version')}, this code reads {VERSION}")
    for key in ("spec", "policy", "counters", "rng"):
        if key not in payload:
            raise CheckpointError(f"checkpoint {path}: incomplete, no {key!r} entry")
    check_spec(payload, expect or {}, path)
    return payload


# Spec entries added after checkpoints were first written, with what the checkpoints without them trained with.
SPEC_DEFAULTS: dict[str, Any] = {"shared_encoder": True, "obs_norm": False, "feature_norm": False,
                                 "central_critic": False}
# Spec entries that are keys of the config's train section.
TRAIN_SPEC_KEYS = frozenset({"shared_policy", "feature_dim", "head_hidden", "shared_encoder", "obs_norm",
                             "feature_norm", "central_critic"})


def check_spec(payload: dict[str, Any], expect: dict[str, Any], path: Path) -> None:
    """Raise `CheckpointError` naming `path` unless the payload's spec matches every `expect` entry."""
    spec = payload["spec"]
    for key, want in expect.items():
        have = spec.get(key, SPEC_DEFAULTS.get(key))
        if _norm(have) != _norm(want):
            # The network's train keys: the way to a run the checkpoint fits is to set the key as it trained.
            way = (f" (it trained with train.{key}={str(have).lower() if isinstance(have, bool) else have})"
                   if key in TRAIN_SPEC_KEYS else "")
            raise CheckpointError(f"checkpoint {path}: incompatible {key}: checkpoint has {have!r}, "
                                  f"this run needs {want!r}{way}")


def _norm(value: Any) -> Any:
    return [_norm(v) for v in value] if isinstance(value, list | tuple) else value


def rng_state() -> dict[str, Any]:
    """Python, numpy and torch RNG states in types `torch.load(weights_only=True)` accepts."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    return {"python": random.getstate(), "numpy": [kind, torch.from_numpy(keys.astype(np.int64)), pos,
                                                   has_gauss, cached], "torch": torch.get_rng_state()}


def set_rng_state(state: dict[str, Any]) -> None:
    kind, keys, pos, has_gauss, cached = state["numpy"]
    random.setstate(_tuples(state["python"]))
    np.random.set_state((kind, keys.numpy().astype(np.uint32), pos, has_gauss, cached))
    torch.set_rng_state(state["torch"])


def _tuples(value: Any) -> Any:
    return tuple(_tuples(v) for v in value) if isinstance(value, list | tuple) else value


def build_net(spec: dict[str, Any]) -> ActorCritic:
    return ActorCritic(tuple(spec["obs_shape"]), spec["n_actions"], feature_dim=spec["feature_dim"],
                       head_hidden=spec["head_hidden"],
                       shared_encoder=spec.get("shared_encoder", SPEC_DEFAULTS["shared_encoder"]),
                       obs_norm=spec.get("obs_norm", SPEC_DEFAULTS["obs_norm"]),
                       feature_norm=spec.get("feature_norm", SPEC_DEFAULTS["feature_norm"]),
                       central_critic=spec.get("central_critic", SPEC_DEFAULTS["central_critic"]))


def _checked_policy_file(payload: Any, path: Path) -> dict[str, Any]:
    if not isinstance(payload, dict) or payload.get("version") != VERSION or "nets" not in payload:
        raise CheckpointError(f"policy file {path}: not a {POLICY_FORMAT} file of version {VERSION}")
    return payload


def load_policy(path: str | Path, device: str = "cpu") -> tuple[dict[str, ActorCritic], dict[str, Any]]:
    """Trained policies of a run, one per agent name, and the checkpoint's metadata (see module doc). `path`: a
    run folder (its policy file, else its checkpoint), a policy file or a checkpoint."""
    path = Path(path)
    if path.is_dir():
        path = path / POLICY_NAME if (path / POLICY_NAME).is_file() else path / CHECKPOINT_NAME
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path}: not found")
    payload = _load(path)
    # By its content, whatever its name: a shipped or exported policy file may be called anything.
    if isinstance(payload, dict) and payload.get("format") == POLICY_FORMAT:
        payload = _checked_policy_file(payload, path)
        state = payload["nets"]
    else:
        payload = _checked_checkpoint(payload, path)
        state = played_nets(payload["policy"])
    spec = payload["spec"]
    try:
        nets = []
        for sd in state:
            net = build_net(spec)
            net.load_state_dict(sd)
            nets.append(net.to(device).eval())
    except (KeyError, RuntimeError, ValueError) as exc:
        raise CheckpointError(f"checkpoint {path}: networks do not match its spec ({exc})") from None
    agents = list(spec["agents"])
    if len(nets) != (1 if spec["shared_policy"] else len(agents)):
        raise CheckpointError(f"checkpoint {path}: {len(nets)} networks for {len(agents)} agents")
    policies = {a: nets[0 if spec["shared_policy"] else i] for i, a in enumerate(agents)}
    meta = {"path": str(path), "spec": spec, "counters": payload["counters"],
            "train": payload.get("train", {}), "config": payload.get("config", {}), "phis": payload.get("phis"),
            "validation": payload.get("validation")}
    return policies, meta


@torch.no_grad()
def act_agents(policies: Mapping[str, ActorCritic], obs: Mapping[str, np.ndarray], greedy: bool,
               masks: Mapping[str, np.ndarray] | None = None) -> dict[str, int]:
    """Each agent's action for its observation (F, C, H, W), among those its mask (A,) allows where `masks` are
    given (an agent without one, done already, whose action the env ignores, acts unmasked); agents sharing a
    network act in one batch.

    (`agents.multiagent.MultiAgentPolicy.act` batches the same way during training, but samples only and
    follows the learner schedule of a training run's networks.)"""
    groups: dict[int, list[str]] = {}
    for a in obs:
        groups.setdefault(id(policies[a]), []).append(a)
    actions = {}
    for names in groups.values():
        batch = np.stack([obs[a] for a in names])  # (B, F, C, H, W)
        net = policies[names[0]]
        if masks is None:  # any actor with `ActorCritic.act`'s signature (agents.sb3.Sb3Actor too)
            got = net.act(batch, greedy=greedy)
        else:
            got = net.act(batch, greedy=greedy,
                          mask=np.stack([masks.get(a, np.ones(net.n_actions, np.int8)) for a in names]))  # (B, A)
        actions.update(zip(names, got.tolist(), strict=True))
    return actions


@dataclass(frozen=True)
class TrainedPolicy:
    """A trained run's networks as a policy of `cosim.evaluation.runner.evaluate` (its `Policy` protocol)."""

    checkpoint: str  # a checkpoint.pt or policy.pt
    greedy: bool = True  # argmax actions; false: sampled
    name: ClassVar[str] = "checkpoint"
    overrides: ClassVar[Mapping[str, Any]] = {}

    def identity(self) -> dict[str, Any]:
        # Which state of the run is evaluated: a run trained further must not resume its old evaluation. The
        # file's content, not its path, says which weights: the same policy cloned elsewhere resumes its folder.
        updates = load_policy(self.checkpoint)[1]["counters"].get("updates")
        sha = file_sha256(self.checkpoint)
        return {"checkpoint": self.checkpoint, "greedy": self.greedy,
                "trained_updates": None if updates is None else int(updates), "model_sha256": sha}

    def load(self, env: ParallelEnv, worker: bool) -> Callable[[int], Callable[[Mapping[str, np.ndarray]], dict]]:
        if worker:
            torch.set_num_threads(1)  # W evaluation workers on W cores
        nets, meta = load_policy(self.checkpoint)
        return episode_actors(nets, meta["spec"], env, self.checkpoint, self.greedy,
                              masked=bool(meta["train"].get("action_mask", False)))


def episode_actors(nets: Mapping[str, Any], spec: Mapping[str, Any], env: ParallelEnv, path: str | Path,
                   greedy: bool, masked: bool = False) -> Callable[[int], Callable[[Mapping[str, np.ndarray]], dict]]:
    """Episode seed -> (observations -> actions) of networks checked against the env's observations and agents;
    seeded per episode, so that sampled actions do not depend on which worker plays it; `masked`: among the
    actions the env's `action_masks()` allow (the masks of its infos, read when the actions are asked for)."""
    agents = env.possible_agents
    if not agents:  # demand without AVs (av_penetration 0): nothing to act for, as with a baseline
        return lambda seed: lambda obs: {}
    shape = tuple(env.observation_space(agents[0]).shape)
    if tuple(spec["obs_shape"]) != shape:
        raise CheckpointError(
            f"checkpoint {path}: observations of shape {tuple(spec['obs_shape'])}, but this net/preset gives "
            f"{shape} (observation preset {env.cfg.observation.preset!r}); evaluate with the run's config")
    if spec["n_actions"] != env.action_space(agents[0]).n:
        raise CheckpointError(f"checkpoint {path}: trained with {spec['n_actions']} actions; this scenario has "
                              f"{env.action_space(agents[0]).n}")
    if spec["shared_policy"]:  # one ego-centred network serves every AV, however many the scenario has
        nets = dict.fromkeys(agents, next(iter(nets.values())))
    missing = [a for a in agents if a not in nets]
    if missing:
        more = ", coming and going" if len(agents) > len(nets) else ""
        raise CheckpointError(
            f"checkpoint {path}: one network per AV (train.shared_policy: false), for {sorted(nets)}; this scenario "
            f"has {len(agents)} AVs ({agents[0]} .. {agents[-1]}{more}): a per-AV network serves only the AV it "
            "was trained for; train with a shared network (the default)")

    def for_episode(seed: int) -> Callable[[Mapping[str, np.ndarray]], dict]:
        torch.manual_seed(seed)
        return lambda obs: act_agents(nets, obs, greedy, env.action_masks() if masked else None)

    return for_episode


def describe_checkpoint(path: Path) -> str:
    """Which state of a run `path` holds, in words: its episodes, and for a best.pt the validation that chose it."""
    meta = load_policy(path)[1]
    counters, row = meta["counters"], meta["validation"]
    trained = ", ".join(f"{int(counters[k]):,} {k}" for k in ("episodes", "updates") if k in counters)
    what = f"{path}, trained {trained}" if trained else str(path)
    if row is None:
        return what
    return (f"{what}, the best validation of its run ({int(row['episodes_validated'])} greedy "
            f"{'runs' if 'collisions' in row else 'episodes'} on the validation seeds: {describe(row)})")


def run_record(run: Path) -> dict[str, Any]:
    """A run folder's `NET_RECORD` (empty where it has none)."""
    path = Path(run) / NET_RECORD
    return json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {}


def first_seed(run: Path) -> int | None:
    """The training seed of a run folder's first part, where it was joined onto the run it continues
    (scripts/snapshot_run.py --continues: a continuation trains with a seed of its own); None for a run of one part."""
    seed = run_record(run).get("continues", {}).get("train_seed")
    return None if seed is None else int(seed)


def find_checkpoint(run: Path | None, checkpoint: Path | None, last: bool = False) -> Path:
    """The file to evaluate: `checkpoint`, else the run's best policy by validation (`best.pt`) where it kept one
    and `last` is not asked for, else its last policy file (the networks alone), else its resumable checkpoint;
    `CosimError` when there is none."""
    if run is None and checkpoint is None:
        raise CosimError("cosim evaluate: give --run RUN (or --checkpoint FILE) for a trained policy, "
                         "or --policy BASELINE")
    names = (POLICY_NAME, CHECKPOINT_NAME) if last else (BEST_NAME, POLICY_NAME, CHECKPOINT_NAME)
    path = checkpoint or next((run / n for n in names if (run / n).is_file()), run / CHECKPOINT_NAME)
    if not path.is_file():
        raise CosimError(f"checkpoint {path}: not found; train the run first (cosim train), pass "
                         f"--checkpoint FILE, or evaluate a baseline with --policy")
    return path.resolve()
