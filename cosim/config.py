"""Typed experiment config: frozen dataclasses loaded from YAML, validated once at load.

Contract: `load_config(path_or_dict, overrides)` returns a `Config` or raises `ConfigError` naming the bad
key. Unknown keys are errors; dotted overrides (`{"reward.phi": 0.785}` or `["reward.phi=0.785"]`) are
applied before validation. Relative paths in `net` are resolved against the YAML file's folder.
Units are given in each field's comment.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from cosim.environment.reward import TERMS
from cosim.errors import ConfigError

# A stacked VelocityMap of the paper's size vs one that trains on a CPU; user keys override a preset.
OBSERVATION_PRESETS: dict[str, dict[str, Any]] = {
    "default": {"frames": 5, "height_px": 32, "width_px": 128, "length_m": 128.0, "width_m": 32.0},
    "paper": {"frames": 10, "height_px": 64, "width_px": 512, "length_m": 256.0, "width_m": 32.0},
}
CHANNELS = ("road", "avs", "hvs", "ego_merger")
# Episode seeds from here on are evaluation's; training draws its seeds below, so the two never meet.
EVAL_SEED_START = 10_000_000
AV_DRIVERS = ("env", "sumo")  # who drives the AVs: the agents through the env, or SUMO's own models
PLACEMENTS = ("window", "stream")  # keys of cosim.sumo.scenario.PLACEMENTS
ON_COLLISION = ("end", "remove")  # a collision with an AV or the merging vehicle ends the episode, or is removed


# The bundled 2-lane merge with a long approach (sumo_net/dilemma), the net of every config that names none.
DEFAULT_NET = Path(__file__).resolve().parents[1] / "sumo_net" / "dilemma" / "dilemma.net.xml"
# HVs that never yield to the merging vehicle and keep their lane: no cooperative lane changes or speed
# adjustments, no lane changes for speed or to keep right (LC2013 / SL2015 parameters).
NON_YIELDING: dict[str, float] = {"lcCooperative": 0.0, "lcSpeedGain": 0.0, "lcKeepRight": 0.0}


@dataclass(frozen=True)
class NetConfig:
    file: str = str(DEFAULT_NET)  # the SUMO .net.xml (in a YAML file: relative to that file)
    # Net description YAML; None: `<net stem>.yaml` beside the net, else inferred from the net.
    description: str | None = None


@dataclass(frozen=True)
class SimConfig:
    step_length: float = 0.1  # [s] SUMO step; 0.1 s so side collisions are not stepped over
    decision_period: float = 1.0  # [s] between two agent decisions
    horizon: float = 20.0  # [s] episode time limit (truncation)
    seed: int = 0  # seed of the first episode; each reset without a seed takes the next one
    collision_mingap_factor: float = 0.0  # 0: only physical overlap is a collision
    # What a collision that involves an AV or the merging vehicle does: "end" the episode at that SUMO step
    # (the paper's rule; the wrecks stay where they are), or "remove" the colliders after the decision step
    # and go on. Collisions among HVs alone never end an episode.
    on_collision: str = "end"
    # [s] a collision within this time after one of the two vehicles entered its lane is a lane-change
    # collision, the fault of the vehicle that changed lanes (crash attribution, cosim.environment.collisions).
    cut_in_window: float = 2.0
    stuck_speed: float = 0.5  # [m/s] a merging vehicle slower than this near its lane end has failed
    stuck_distance: float = 10.0  # [m] ... and this close to the end of the acceleration lane
    # End the episode when the merging vehicle is stuck. Off by default: it then waits there until the horizon,
    # as in the paper, and its lost utility shows in the altruistic AVs' rewards (a cut episode would hide it
    # behind the critic's bootstrap value).
    end_on_stuck: bool = False
    sumo_args: tuple[str, ...] = ()  # extra SUMO command-line options
    # SUMO's own outputs per episode (tripinfo, induction loops), parsed into env.sumo_outputs[seed].
    outputs: bool = False
    output_dir: str | None = None  # folder of the per-episode output folders; None: a temp folder
    detector_offset: float = 100.0  # [m] induction loops this far past the last highway edge's start
    av_driver: str = "env"  # env: the agents' actions drive the AVs; sumo: SUMO's models (a baseline)


@dataclass(frozen=True)
class ScenarioConfig:
    """Where the vehicles start (cosim.sumo.scenario). Ranges [low, high] are drawn uniformly per episode seed.

    `placement: stream` (the merge dilemma): a dense stream of HVs and the AVs in the lane the merging vehicle
    must enter, each HV at its IDM equilibrium gap behind its leader at the stream's speed, led by a vehicle
    that drives at that speed; the stream reaches from `stream_head` back to `place_from`; one AV reaches the
    merge edge `guide_window` after the merging vehicle. `n_hvs` more HVs go on the other through lanes by the
    window rule. `placement: window` (free flow): `n_avs + n_hvs` vehicles spread over every through lane in
    [place_from, place_to] with front-to-front gaps in [min_gap, max_gap] and speeds in `speed_range`.
    """

    placement: str = "stream"  # stream | window
    n_avs: int = 4  # autonomous vehicles (the agents)
    n_hvs: int = 10  # HVs placed by the window rule (stream: on the lanes beside the stream)
    place_from: float = 0.0  # [m] along the highway from its first edge's start
    place_to: float = 640.0  # [m] upstream placement window end
    min_gap: float = 30.0  # [m] front-to-front spacing between window-placed vehicles in a lane, at least
    max_gap: float = 60.0  # [m] ... and at most
    speed_range: tuple[float, float] = (23.0, 28.0)  # [m/s] initial speeds of window-placed vehicles
    merger_pos: tuple[float, float] = (0.0, 40.0)  # [m] start position along the ramp's first edge
    merger_speed: tuple[float, float] = (18.0, 22.0)  # [m/s]
    inflow: float = 0.0  # [veh/h] further HVs entering the highway start during the episode
    stream_speed: tuple[float, float] = (23.0, 27.0)  # [m/s] the stream's speed
    stream_head: tuple[float, float] = (0.0, 80.0)  # [m] its first vehicle, past the merge edge's start
    stream_spacing: tuple[float, float] = (1.0, 1.2)  # [-] factor on each HV's equilibrium gap
    av_speed_offset: tuple[float, float] = (-1.0, 3.0)  # [m/s] AVs' initial speed minus the stream's
    # [s] one AV's arrival at the merge edge minus the merging vehicle's (both at their initial speeds)
    guide_window: tuple[float, float] = (0.0, 3.0)


@dataclass(frozen=True)
class DriverConfig:
    """A vehicle type; HVs and the merging vehicle are driven by SUMO's models."""

    accel: float = 2.6  # [m/s^2]
    decel: float = 4.5  # [m/s^2]
    emergency_decel: float = 9.0  # [m/s^2]
    max_speed: float = 33.0  # [m/s]
    length: float = 5.0  # [m]
    width: float = 1.8  # [m]
    min_gap: float = 2.5  # [m]
    car_follow_model: str = "IDM"
    lane_change_model: str = "LC2013"  # or SL2015
    speed_factor: tuple[float, float] = (0.95, 1.1)  # [-] desired speed / speed limit, drawn per vehicle
    # [s] per-vehicle desired time headway, drawn uniformly; IDM's T. 0.5-0.9 s: a dense stream (front-to-front
    # about 1-1.5 s at its equilibrium gap), the low end of real motorway traffic.
    tau_range: tuple[float, float] = (0.5, 0.9)
    sigma_range: tuple[float, float] = (0.0, 0.3)  # [-] per-vehicle imperfection (Krauss models; IDM has none)
    # LC2013 / SL2015 parameters, e.g. {lcCooperative: 0.2}; the default never yields to the merging vehicle.
    lc_params: Mapping[str, float] = field(default_factory=lambda: dict(NON_YIELDING))


@dataclass(frozen=True)
class AVConfig:
    accel: float = 3.0  # [m/s^2] applied by the env: SUMO's own limits are off for AVs
    decel: float = 5.0  # [m/s^2]
    max_speed: float = 33.0  # [m/s]
    speed_step: float = 2.5  # [m/s] target-speed change of accelerate / decelerate
    length: float = 5.0  # [m]
    width: float = 1.8  # [m]


@dataclass(frozen=True)
class ObservationConfig:
    preset: str = "default"  # one of OBSERVATION_PRESETS; the size keys below override it
    channels: tuple[str, ...] = CHANNELS
    frames: int | None = None  # stacked frames
    height_px: int | None = None  # lateral pixels
    width_px: int | None = None  # longitudinal pixels
    length_m: float | None = None  # [m] longitudinal extent of the window
    width_m: float | None = None  # [m] lateral extent of the window
    ego_at: float = 0.5  # ego's longitudinal place in the window, 0 = rear edge, 1 = front edge
    speed_scale: float = 15.0  # [m/s] relative speed that moves a pixel by 1
    dtype: str = "float32"  # float32 | float16 | uint8

    def __post_init__(self) -> None:
        preset = OBSERVATION_PRESETS.get(self.preset)
        if preset is None:
            raise ConfigError(
                f"observation.preset: unknown preset {self.preset!r}; expected one of {sorted(OBSERVATION_PRESETS)}"
            )
        for key, value in preset.items():
            if getattr(self, key) is None:
                object.__setattr__(self, key, value)


@dataclass(frozen=True)
class RewardConfig:
    # SVO angle [rad]: one value for all AVs, or one per AV. 0 egoistic, pi/4 altruistic, pi/2 fully.
    phi: float | tuple[float, ...] = 0.0
    # Weights of the named utility terms (cosim.environment.reward.TERMS); unlisted terms keep their default.
    weights: Mapping[str, float] = field(default_factory=dict)

    def weight(self, term: str) -> float:
        return float(self.weights.get(term, TERMS[term].weight))


@dataclass(frozen=True)
class Config:
    net: NetConfig = field(default_factory=NetConfig)
    sim: SimConfig = field(default_factory=SimConfig)
    scenario: ScenarioConfig = field(default_factory=ScenarioConfig)
    hv: DriverConfig = field(default_factory=DriverConfig)
    merger: DriverConfig = field(default_factory=lambda: DriverConfig(
        max_speed=30.0, tau_range=(1.0, 1.0), sigma_range=(0.0, 0.0), speed_factor=(1.0, 1.0), lc_params={}))
    av: AVConfig = field(default_factory=AVConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    # Sections owned by later stages (trainer, evaluation): kept as validated-by-them mappings.
    train: Mapping[str, Any] = field(default_factory=dict)
    evaluate: Mapping[str, Any] = field(default_factory=dict)
    source: str | None = None  # the YAML file this came from, if any

    @property
    def steps_per_decision(self) -> int:
        return max(1, round(self.sim.decision_period / self.sim.step_length))

    def phis(self) -> tuple[float, ...]:
        """The SVO angle of each AV [rad]."""
        phi = self.reward.phi
        return tuple(phi) if isinstance(phi, tuple) else (float(phi),) * self.scenario.n_avs

    def to_dict(self) -> dict[str, Any]:
        """A plain dict that `load_config` turns back into an equal config (paths stay resolved)."""
        out = _plain(self)  # not dataclasses.asdict: it deep-copies, and read-only mappings cannot be copied
        out.pop("source")
        return out


def _plain(value: Any) -> Any:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: _plain(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def load_config(
    config: str | Path | Mapping[str, Any] | Config | None = None,
    overrides: Mapping[str, Any] | Sequence[str] | None = None,
) -> Config:
    """Load and validate a config from a YAML path, a dict, or an existing `Config`, applying overrides."""
    source = None
    if config is None:
        data: dict[str, Any] = {}
    elif isinstance(config, Config):
        data, source = config.to_dict(), config.source
    elif isinstance(config, Mapping):
        data = _plain(config)
    else:
        path = Path(config)
        data, source = _read_yaml(path), str(path)
    for key, value in _parse_overrides(overrides).items():
        _set_dotted(data, key, value)
    cfg = _build(Config, data, "")
    net = cfg.net
    # Paths from overrides or dicts are relative to the working directory, as on a command line.
    net = dataclasses.replace(
        net,
        file=str(_resolve(net.file, Path.cwd())),
        description=None if net.description is None else str(_resolve(net.description, Path.cwd())),
    )
    cfg = dataclasses.replace(cfg, net=net, source=source)
    validate(cfg)
    return cfg


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A YAML config as a dict; `base: other.yaml` (relative to this file) is read first and this file's
    keys are merged over it, so experiments state only what differs."""
    if not path.is_file():
        raise ConfigError(f"config file {path}: not found")
    try:
        loaded = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path}: not valid YAML ({exc})") from None
    if loaded is not None and not isinstance(loaded, dict):
        raise ConfigError(f"config file {path}: expected a mapping of sections at top level")
    data = loaded or {}
    net = data.get("net")
    if isinstance(net, dict):  # paths in a file are relative to that file
        for key in ("file", "description"):
            if isinstance(net.get(key), str):
                net[key] = str(_resolve(net[key], path.resolve().parent))
    base = data.pop("base", None)
    if base is None:
        return data
    base_path = (path.resolve().parent / str(base)).resolve()
    if base_path in seen:
        raise ConfigError(f"config file {path}: base {base} includes itself")
    merged = _read_yaml(base_path, (*seen, path.resolve()))
    _merge(merged, data)
    return merged


def _merge(into: dict[str, Any], over: Mapping[str, Any]) -> None:
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(into.get(key), dict):
            _merge(into[key], value)
        else:
            into[key] = value


def _resolve(path: str, base: Path) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() else (base / p).resolve()


def _parse_overrides(overrides: Mapping[str, Any] | Sequence[str] | None) -> dict[str, Any]:
    if overrides is None:
        return {}
    if isinstance(overrides, Mapping):
        return dict(overrides)
    parsed = {}
    for item in overrides:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"override {item!r}: expected KEY=VALUE, e.g. reward.phi=0.785")
        parsed[key.strip()] = yaml.safe_load(raw)
    return parsed


def _set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    node = data
    *parents, leaf = key.split(".")
    for i, part in enumerate(parents):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"override {key}: {'.'.join(parents[: i + 1])} is not a section")
        node = child
    node[leaf] = value


def parse_section(cls: type, data: Any, where: str) -> Any:
    """Validate a mapping into the frozen dataclass `cls`: unknown keys and wrong types are `ConfigError`s
    naming `where.key`. Later stages (trainer, evaluation) validate their own config sections with it."""
    return _build(cls, data if data is not None else {}, where)


def _build(cls: type, data: Any, where: str) -> Any:
    if not isinstance(data, Mapping):
        raise ConfigError(f"{where or 'config'}: expected a mapping, got {type(data).__name__}")
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = set(data) - set(fields) - {"source"}
    if unknown:
        name = sorted(unknown)[0]
        raise ConfigError(
            f"config key {where + '.' if where else ''}{name}: unknown; expected one of {sorted(fields)}"
        )
    kwargs = {}
    for name, value in data.items():
        if name == "source":
            continue
        kwargs[name] = _coerce(hints[name], value, f"{where + '.' if where else ''}{name}")
    try:
        return cls(**kwargs)
    except TypeError as exc:  # pragma: no cover - dataclass signature mismatch is a bug
        raise ConfigError(f"{where or 'config'}: {exc}") from None


def _coerce(tp: Any, value: Any, where: str) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, where)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        if value is None and type(None) in options:
            return None
        for option in options:
            if option is type(None):
                continue
            try:
                return _coerce(option, value, where)
            except ConfigError:
                pass
        allowed = " or ".join(_describe(o) for o in options)
        raise ConfigError(f"{where}: expected {allowed}, got {value!r}")
    if origin is tuple:
        args = typing.get_args(tp)
        if not isinstance(value, list | tuple):
            raise ConfigError(f"{where}: expected a list, got {value!r}")
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(args[0], v, f"{where}[{i}]") for i, v in enumerate(value))
        if len(value) != len(args):
            raise ConfigError(f"{where}: expected {len(args)} values, got {len(value)}")
        return tuple(_coerce(a, v, f"{where}[{i}]") for i, (a, v) in enumerate(zip(args, value, strict=True)))
    if origin in (Mapping, dict) or tp is Mapping:
        if not isinstance(value, Mapping):
            raise ConfigError(f"{where}: expected a mapping, got {value!r}")
        args = typing.get_args(tp)
        vt = args[1] if args else Any
        return types.MappingProxyType({str(k): _coerce(vt, v, f"{where}.{k}") for k, v in value.items()})
    if tp is Any:
        return value
    if tp is float:
        if isinstance(value, str):  # YAML 1.1 reads 1e-4 (no dot) as a string
            try:
                value = float(value)
            except ValueError:
                raise ConfigError(f"{where}: expected a number, got {value!r}") from None
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise ConfigError(f"{where}: expected a number, got {value!r}")
        return float(value)
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where}: expected an integer, got {value!r}")
        return value
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{where}: expected true or false, got {value!r}")
        return value
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(f"{where}: expected a string, got {value!r}")
        return value
    raise ConfigError(f"{where}: unsupported type {tp}")  # pragma: no cover


def _describe(tp: Any) -> str:
    """How an error message names a type: 'a number', 'a list of numbers', 'null'."""
    if tp is type(None):
        return "null"
    if typing.get_origin(tp) is tuple:
        return f"a list of {_describe(typing.get_args(tp)[0]).removeprefix('a ').removeprefix('an ')}s"
    return {float: "a number", int: "an integer", bool: "true or false", str: "a string"}.get(tp, "a mapping")


def validate(cfg: Config) -> None:
    """Cross-field checks that a single field's type cannot express."""
    sc, sim, obs = cfg.scenario, cfg.sim, cfg.observation

    def positive(where: str, value: float, strict: bool = True) -> None:
        if value < 0 or (strict and value == 0):
            raise ConfigError(f"{where}: must be {'> 0' if strict else '>= 0'}, got {value}")

    positive("scenario.n_avs", sc.n_avs)
    positive("scenario.n_hvs", sc.n_hvs, strict=False)
    positive("scenario.inflow", sc.inflow, strict=False)
    positive("scenario.min_gap", sc.min_gap)
    positive("sim.step_length", sim.step_length)
    positive("sim.decision_period", sim.decision_period)
    positive("sim.horizon", sim.horizon)
    positive("sim.detector_offset", sim.detector_offset, strict=False)
    positive("sim.cut_in_window", sim.cut_in_window, strict=False)
    if sim.on_collision not in ON_COLLISION:
        raise ConfigError(f"sim.on_collision: expected one of {list(ON_COLLISION)}, got {sim.on_collision!r}")
    if sc.placement not in PLACEMENTS:
        raise ConfigError(f"scenario.placement: expected one of {list(PLACEMENTS)}, got {sc.placement!r}")
    if sim.av_driver not in AV_DRIVERS:
        raise ConfigError(f"sim.av_driver: expected one of {list(AV_DRIVERS)}, got {sim.av_driver!r}")
    if sim.decision_period < sim.step_length:
        raise ConfigError("sim.decision_period: must be at least sim.step_length")
    steps = sim.decision_period / sim.step_length
    if abs(steps - round(steps)) > 1e-6:
        raise ConfigError(f"sim.decision_period: must be a whole number of SUMO steps (sim.step_length = "
                          f"{sim.step_length} s), got {sim.decision_period} s = {steps:.3g} steps")
    if sc.max_gap < sc.min_gap:
        raise ConfigError(f"scenario.max_gap: must be >= scenario.min_gap ({sc.min_gap}), got {sc.max_gap}")
    if sc.place_to <= sc.place_from:
        raise ConfigError("scenario.place_to: must be greater than scenario.place_from")
    for name in ("speed_range", "merger_speed", "merger_pos", "stream_speed", "stream_spacing"):
        lo, hi = getattr(sc, name)
        if not 0 <= lo <= hi:
            raise ConfigError(f"scenario.{name}: expected [low, high] with 0 <= low <= high, got {[lo, hi]}")
    for name in ("stream_head", "av_speed_offset", "guide_window"):
        lo, hi = getattr(sc, name)
        if not lo <= hi:
            raise ConfigError(f"scenario.{name}: expected [low, high] with low <= high, got {[lo, hi]}")
    if sc.stream_spacing[0] < 1.0:
        raise ConfigError(f"scenario.stream_spacing: expected factors >= 1 (below the equilibrium gap the "
                          f"stream brakes at once), got {list(sc.stream_spacing)}")
    for section in ("hv", "merger"):
        drv: DriverConfig = getattr(cfg, section)
        for name in ("tau_range", "sigma_range", "speed_factor"):
            lo, hi = getattr(drv, name)
            if not 0 <= lo <= hi:
                raise ConfigError(f"{section}.{name}: expected [low, high] with 0 <= low <= high")
        if drv.lane_change_model not in ("LC2013", "SL2015"):
            raise ConfigError(f"{section}.lane_change_model: expected LC2013 or SL2015, got "
                              f"{drv.lane_change_model!r}")
    for name in ("accel", "decel", "max_speed", "speed_step"):
        positive(f"av.{name}", getattr(cfg.av, name))
    for name in ("frames", "height_px", "width_px", "length_m", "width_m", "speed_scale"):
        positive(f"observation.{name}", getattr(obs, name))
    if not 0.0 <= obs.ego_at <= 1.0:
        raise ConfigError(f"observation.ego_at: must be within [0, 1], got {obs.ego_at}")
    bad = [c for c in obs.channels if c not in CHANNELS]
    if bad or not obs.channels or len(set(obs.channels)) != len(obs.channels):
        raise ConfigError(f"observation.channels: expected distinct names from {list(CHANNELS)}, got "
                          f"{list(obs.channels)}")
    if obs.dtype not in ("float32", "float16", "uint8"):
        raise ConfigError(f"observation.dtype: expected float32, float16 or uint8, got {obs.dtype!r}")
    unknown_terms = sorted(set(cfg.reward.weights) - set(TERMS))
    if unknown_terms:
        raise ConfigError(f"reward.weights.{unknown_terms[0]}: unknown term; expected one of {sorted(TERMS)}")
    phis = cfg.reward.phi
    if isinstance(phis, tuple) and len(phis) != sc.n_avs:
        raise ConfigError(f"reward.phi: a list needs one angle per AV ({sc.n_avs}), got {len(phis)}")
    for phi in phis if isinstance(phis, tuple) else (phis,):
        if not -math.pi <= phi <= math.pi:
            raise ConfigError(f"reward.phi: expected an angle in radians within [-pi, pi], got {phi}")
