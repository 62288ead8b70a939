"""Typed experiment config: frozen pydantic models loaded from YAML, validated once at load.

Contract: `load_config(path_or_dict_or_Config, overrides)` returns a `Config` or raises `ConfigError` with one
line per problem, each naming the dotted key (`scenario.n_avs`, `train.lr`) and what is allowed (the bounds,
the choices, or for an unknown key the section's keys), prefixed with where the value came from: the
`--set KEY=VALUE` that gave it (an override given as a string; one given in a dict is code's, named by its key
alone), else the file when loaded from one. A YAML file's `base:` chain and the overrides
(`{"reward.phi": 0.785}` or `["reward.phi=0.785"]`, values read as YAML scalars) are merged into one raw dict
that one `Config.model_validate` checks, so a value is judged the same wherever it came from. Unknown keys are
errors; missing keys keep the defaults. Relative paths in `net` are resolved against the YAML file's folder (in
an override or a dict: against the working directory). A file
must be UTF-8 YAML with no key given twice in a mapping (`read_yaml`, for every YAML file a user may have
edited); a file or override that is not is one line naming it and the position. Each field declares its
default, bounds and unit (`[unit]` ending its description) in one place, which `Config.model_json_schema()`
shows. Cross-field rules: a decision is a whole number of SUMO steps
and the horizon a whole number of decisions; one agent's observation holds at most `MAX_OBSERVATION_VALUES`.
Every section, `train:` and `evaluate:` included, is typed here; the module does not import torch, so rollout
workers and the CLI read it cheaply.

Seeds: `check_seed(name, seed, count)` is the one check of an episode seed (0 .. `SEED_MAX`, what SUMO's
`--seed` takes), behind the seed keys, the command-line seed flags and `MergeEnv.reset(seed=...)`. Training
episodes draw their seeds below `EVAL_SEED_START`, evaluation's default first seed.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Annotated, Any, ClassVar, Literal, Self, TypeVar, get_args

import yaml
from pydantic import (
    AfterValidator,
    AllowInfNan,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    PlainSerializer,
    Strict,
    StrictBool,
    StrictStr,
    ValidationError,
    ValidatorFunctionWrapHandler,
    WrapValidator,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from cosim.errors import ConfigError, SeedError

# A stacked VelocityMap of the paper's size vs one that trains on a CPU; user keys override a preset.
OBSERVATION_PRESETS: dict[str, dict[str, Any]] = {
    "default": {"frames": 5, "height_px": 32, "width_px": 128, "length_m": 128.0, "width_m": 32.0},
    "paper": {"frames": 10, "height_px": 64, "width_px": 512, "length_m": 256.0, "width_m": 32.0},
}
# Episode seeds from here on are evaluation's; training draws its seeds below, so the two never meet.
EVAL_SEED_START = 10_000_000
# Validation during training (`train.eval_every`) plays seeds from here: far above evaluation's, so that choosing a
# run's best checkpoint never looks at the episodes it is then tested on.
VALIDATION_SEED_START = 2_000_000_000
# The largest episode seed: SUMO's --seed is a 32-bit signed integer (and numpy's SeedSequence, which the
# scenario draws from, takes no negative one), so seeds are 0 .. SEED_MAX.
SEED_MAX = 2**31 - 1
# Values of one agent's stacked observation (frames x channels x height x width), at most: 12.8 times the
# paper preset's 1,310,720 (10 x 4 x 64 x 512). At float32 that is 64 MiB per agent; each worker's VelocityMapper
# keeps two stacks per AV (its ring of frames), and a training batch one per AV and decision step, so a larger
# observation cannot train on one machine, and a mistyped size would otherwise fail in numpy's allocation.
MAX_OBSERVATION_VALUES = 2**24
# The bundled 2-lane merge with a long approach (sumo_net/dilemma), the net of every config that names none.
DEFAULT_NET = Path(__file__).resolve().parents[1] / "sumo_net" / "dilemma" / "dilemma.net.xml"
# The experiment a command runs without --config, found from any working directory.
DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "default.yaml"
# HVs that never yield to the merging vehicle and keep their lane: no cooperative lane changes or speed
# adjustments, no lane changes for speed or to keep right (LC2013 / SL2015 parameters).
NON_YIELDING: dict[str, float] = {"lcCooperative": 0.0, "lcSpeedGain": 0.0, "lcKeepRight": 0.0}
# The lane-change parameters each model reads from a vType, as SUMO 1.28's parser and models take them
# (SUMOVehicleParserHelper::parseLCParams; tests/cosim/sumo/test_lc_params.py checks them against the installed
# SUMO). SUMO skips any other attribute without a word, so a misspelt name would change nothing silently.
_LC2013_PARAMS = frozenset({
    "lcStrategic", "lcCooperative", "lcSpeedGain", "lcKeepRight", "lcOpposite", "lcLookaheadLeft", "lcSpeedGainRight",
    "lcMaxSpeedLatStanding", "lcMaxSpeedLatFactor", "lcMaxDistLatStanding", "lcAssertive", "lcSpeedGainLookahead",
    "lcCooperativeRoundabout", "lcCooperativeSpeed", "lcOvertakeRight", "lcSigma", "lcKeepRightAcceptanceTime",
    "lcOvertakeDeltaSpeedFactor", "lcStrategicLookahead", "lcSpeedGainRemainTime"})
LC_PARAMS: dict[str, frozenset[str]] = {
    "LC2013": _LC2013_PARAMS,
    "SL2015": _LC2013_PARAMS | {"lcPushy", "lcPushyGap", "lcSublane", "lcImpatience", "lcTimeToImpatience",
                                "lcAccelLat", "lcTurnAlignmentDistance", "lcLaneDiscipline"},
}

# Enumerated strings: the Literal is what a field accepts, the tuple what other modules list or look up.
Channel = Literal["road", "avs", "hvs", "ego_merger"]
AvDriver = Literal["env", "sumo"]
Placement = Literal["window", "stream"]
OnCollision = Literal["end", "remove"]
Preset = Literal[tuple(OBSERVATION_PRESETS)]  # type: ignore[valid-type]
Algo = Literal["a2c", "ppo"]
OptimizerName = Literal["adam", "rmsprop"]
Precision = Literal["auto", "float32", "bfloat16"]
Shield = Literal["none", "sumo"]
CHANNELS: tuple[str, ...] = get_args(Channel)
AV_DRIVERS: tuple[str, ...] = get_args(AvDriver)  # who drives the AVs: the agents through the env, or SUMO
PLACEMENTS: tuple[str, ...] = get_args(Placement)  # keys of cosim.sumo.scenario.PLACEMENTS
ON_COLLISION: tuple[str, ...] = get_args(OnCollision)
ALGOS: tuple[str, ...] = get_args(Algo)
OPTIMIZER_NAMES: tuple[str, ...] = get_args(OptimizerName)  # keys of agents.losses.OPTIMIZERS
PRECISIONS: tuple[str, ...] = get_args(Precision)
SHIELDS: tuple[str, ...] = get_args(Shield)  # keys of cosim.sumo.session.AV_MODES


def _problem(message: str, key: str = "") -> PydanticCustomError:
    """A problem worded for `ConfigError`; `key`: the field a section's validator blames, below that section."""
    return PydanticCustomError("cosim", "{message}", {"message": message, "key": key})


def _no_bool(value: Any) -> Any:
    # pydantic's lax float reads true as 1.0, which would hide a value put under the wrong key. Strings go on
    # to it: YAML 1.1 reads 1e-4 (no dot) as a string.
    if isinstance(value, bool):
        raise _problem(f"expected a number, got {value!r}")
    return value


def _str_keys(value: Any) -> Any:
    return {str(k): v for k, v in value.items()} if isinstance(value, Mapping) else value


def _as_dict(value: Mapping[str, float]) -> dict[str, float]:
    return dict(value)


# An int key takes no float, bool or string: 2.5 or "3" there is a mistake, not something to round or parse.
Int = Annotated[int, Strict()]
Number = Annotated[float, BeforeValidator(_no_bool), AllowInfNan(False)]
# Read-only, as the rest of a frozen config; serialized as a plain dict.
NumberMap = Annotated[
    Mapping[str, Number], BeforeValidator(_str_keys), AfterValidator(MappingProxyType), PlainSerializer(_as_dict)
]
# The bounds before the validator, so the JSON schema states them (pydantic leaves them raw after it).
Angle = Annotated[float, AllowInfNan(False), Field(ge=-math.pi, le=math.pi), BeforeValidator(_no_bool)]


def check_seed(name: str, seed: Any, count: int = 1) -> int:
    """The one check of an episode seed, whether a config key, a command-line flag or `reset(seed=...)`: `seed`
    as a plain int when it and the `count - 1` seeds after it lie in [0, SEED_MAX], else `SeedError` naming
    `name`. A Python or numpy integer passes; a bool, a float or a string does not."""
    problem = _seed_problem(seed, count)
    if problem:
        raise SeedError(f"{name}: {problem}")
    return int(seed)


def _seed_problem(seed: Any, count: int = 1) -> str | None:
    last = SEED_MAX - count + 1
    if isinstance(seed, numbers.Integral) and not isinstance(seed, bool) and 0 <= seed <= last:
        return None
    fit = f", so that the seeds of all {count} episodes fit" if count > 1 else ""
    return f"expected an integer in [0, {last}]{fit} (SUMO's --seed is a 32-bit signed integer), got {_show(seed)}"


def _seed(seed: int) -> int:
    problem = _seed_problem(seed)
    if problem:
        raise _problem(problem)
    return seed


# A seed key: judged by the same check as a seed flag; the schema states the range.
Seed = Annotated[Int, AfterValidator(_seed), Field(json_schema_extra={"minimum": 0, "maximum": SEED_MAX})]


def _span(least: float | None = None, why: str = "") -> Any:
    """A [low, high] pair with low <= high (and `least` <= low): the range a value is drawn from per episode."""

    def shape(value: Any) -> Any:
        if isinstance(value, list | tuple) and len(value) != 2:
            raise _problem(f"expected [low, high], got {list(value)}")
        return value

    def order(pair: tuple[float, float]) -> tuple[float, float]:
        lo, hi = pair
        if not (lo <= hi and (least is None or least <= lo)):
            rule = "low <= high" if least is None else f"{least:g} <= low <= high"
            raise _problem(f"expected [low, high] with {rule}{why}, got {list(pair)}")
        return pair

    return Annotated[tuple[Number, Number], BeforeValidator(shape), AfterValidator(order)]


Span = _span()
NonNegativeSpan = _span(0.0)
SpacingSpan = _span(1.0, " (below the equilibrium gap the stream brakes at once)")


ShareSpan = _span(0.0)


# Net-relative keys and their absolute twins. Each group lists alternatives, each a tuple of keys that state
# one quantity: the first alternative is net-relative (resolved per net by cosim.sumo.resolve) and holds the
# section's default; the others state it in absolute units. One alternative per config: both in one file or
# one set of overrides is an error; a later layer (a file over its `base:`, an override over the files) that
# sets one alternative clears the others, so `--set scenario.n_hvs=4` works on a config stating hv_density.
Twins = tuple[tuple[str, ...], ...]
SCENARIO_TWINS: tuple[Twins, ...] = (
    (("merger_time",), ("merger_distance",), ("merger_pos",)),
    (("merger_speed_factor",), ("merger_speed",)),
    (("stream_speed_factor",), ("stream_speed",)),
    (("stream_head_share",), ("stream_head",)),
    (("av_speed_offset_factor",), ("av_speed_offset",)),
    (("speed_range_factor",), ("speed_range",)),
    (("place_share",), ("place_from", "place_to")),
    (("hv_density",), ("n_hvs",)),
)
DRIVER_TWINS: tuple[Twins, ...] = ((("max_speed_factor",), ("max_speed",)),)
AV_TWINS: tuple[Twins, ...] = ((("max_speed_factor",), ("max_speed",)), (("speed_step_factor",), ("speed_step",)))
OBSERVATION_TWINS: tuple[Twins, ...] = ((("speed_scale_factor",), ("speed_scale",)),)
DEMAND_TWINS: tuple[Twins, ...] = ((("mainline_share",), ("mainline_vph",)), (("ramp_share",), ("ramp_vph",)),
                                   (("av_penetration",), ("av_count",)))
TWINS: dict[str, tuple[Twins, ...]] = {"scenario": SCENARIO_TWINS, "hv": DRIVER_TWINS, "merger": DRIVER_TWINS,
                                       "av": AV_TWINS, "observation": OBSERVATION_TWINS, "demand": DEMAND_TWINS}


def _given(data: Mapping[str, Any], keys: Sequence[str]) -> bool:
    return any(data.get(k) is not None for k in keys)


def _one_of_twins(data: Any, groups: tuple[Twins, ...]) -> Any:
    """Before a section validates: an error naming both keys where two alternatives are given; where an absolute
    alternative is given, the relative one's default is dropped (null); where none is, it holds."""
    if not isinstance(data, Mapping):
        return data
    data = dict(data)
    for group in groups:
        given = [alt for alt in group if _given(data, alt)]
        if len(given) > 1:
            a, b = given[0][0], given[1][0]
            raise _problem(f"set together with {a}, its twin: the two state one quantity (one relative to the net, "
                           f"one absolute); give one, e.g. set {a} to null", b)
        if given and given[0] is not group[0]:
            data.update(dict.fromkeys((k for k in group[0] if k not in data), None))
        elif not given:  # none stated (a null included): the relative alternative's default
            for k in group[0]:
                data.pop(k, None)
    return data


def _clear_twins(section: str, into: dict[str, Any], over: Mapping[str, Any]) -> None:
    """`over` is merged into `into` (one config section, a later layer over an earlier one): the alternatives
    of each quantity that `over` states are cleared from `into`."""
    for group in TWINS.get(section, ()):
        for alt in group:
            if _given(over, alt):
                for other in group:
                    if other is not alt:
                        for k in other:
                            into.pop(k, None)


def _angles(value: Any, handler: ValidatorFunctionWrapHandler) -> Any:
    # One line for the field instead of pydantic's one per member of the union.
    try:
        return handler(value)
    except ValidationError as exc:
        if any(e["type"] in ("greater_than_equal", "less_than_equal") for e in exc.errors()):
            raise _problem(f"expected an angle in radians within [-pi, pi], got {value!r}") from None
        raise _problem(f"expected a number or a list of numbers, got {value!r}") from None


def _device_problem(device: str) -> str | None:
    kind, _, index = device.partition(":")
    if kind not in ("cpu", "cuda") or (index and (kind != "cuda" or not index.isdigit())):
        return f"expected cpu, cuda or cuda:N, got {device!r}"
    return None


def check_device(device: str, where: str) -> None:
    """Accept cpu, cuda and cuda:N (`ConfigError` naming `where` otherwise); availability is the learner's."""
    problem = _device_problem(device)
    if problem:
        raise ConfigError(f"{where}: {problem}")


class _Section(BaseModel):
    """A frozen config section. `model_validate` raises `ConfigError` (see `_error`); a section built in code
    (`ObservationConfig(frames=3)`) raises pydantic's `ValidationError`, a bug of that code, not user input. No
    custom `__init__` to convert it: pydantic would then call it for every nested section, and the first
    problem would hide the others and lose its key path."""

    model_config = ConfigDict(frozen=True, extra="forbid", validate_default=True)
    twins: ClassVar[tuple[Twins, ...]] = ()  # the section's net-relative keys and their absolute twins (TWINS)

    @model_validator(mode="before")
    @classmethod
    def _one_of_twins(cls, data: Any) -> Any:
        return _one_of_twins(data, cls.twins)

    @classmethod
    def model_validate(cls, obj: Any, **kwargs: Any) -> Self:
        """pydantic's `model_validate`, raising `ConfigError`; `context` may give `where` (the key path of `obj`,
        prefixed to every key named), `source` (the file it came from, prefixed to every line) and `overrides`
        (dotted key -> the `--set KEY=VALUE` that gave it, or "" for one set in code: its lines name that instead
        of the file)."""
        context = kwargs.get("context") or {}
        try:
            return super().model_validate(obj, **kwargs)
        except ValidationError as exc:
            raise _error(exc, cls, context.get("where", ""), context.get("source"),
                         context.get("overrides") or {}) from None


class NetConfig(_Section):
    file: StrictStr = Field(str(DEFAULT_NET), description="the SUMO .net.xml (in a YAML file: relative to that file)")
    description: StrictStr | None = Field(
        None, description="net description YAML; null: `<net stem>.yaml` beside the net, else inferred from the net")

    @field_validator("file", "description")
    @classmethod
    def _absolute(cls, path: str | None) -> str | None:
        # A YAML file's relative paths were made absolute against its folder when it was read (`_read_yaml`);
        # one still relative came from a dict or a command line, as a shell would read it.
        return None if path is None else str(_resolve(path, Path.cwd()))


class SimConfig(_Section):
    step_length: Number = Field(
        0.1, gt=0, le=1.0, description="SUMO step; 0.1 s so side collisions are not stepped over, at most 1 s: at "
        "a 1 s step SUMO already missed one (the two vehicles had passed each other within the step) [s]")
    decision_period: Number = Field(1.0, gt=0, description="between two agent decisions [s]")
    horizon: Number = Field(
        20.0, gt=0, description="episode time limit (truncation), a whole number of decision periods [s]")
    seed: Seed = Field(0, description="seed of the first episode; each reset without a seed takes the next one")
    collision_mingap_factor: Number = Field(0.0, description="0: only physical overlap is a collision [-]")
    on_collision: OnCollision = Field(
        "end", description="what a collision that involves an AV or the merging vehicle does: `end` the episode at "
        "that SUMO step (the paper's rule; the wrecks stay where they are), or `remove` the colliders after the "
        "decision step and go on. Collisions among HVs alone never end an episode.")
    cut_in_window: Number = Field(
        2.0, ge=0, description="a collision within this time after one of the two vehicles entered its lane is a "
        "lane-change collision, the fault of the vehicle that changed lanes (cosim.environment.collisions) [s]")
    stuck_speed: Number = Field(
        0.5, description="a merging vehicle slower than this near its lane end has failed [m/s]")
    stuck_distance: Number = Field(10.0, description="... and this close to the end of the acceleration lane [m]")
    # Off by default: the stuck vehicle then waits there until the horizon, as in the paper, and its lost utility
    # shows in the altruistic AVs' rewards (a cut episode would hide it behind the critic's bootstrap value).
    end_on_stuck: StrictBool = Field(False, description="end the episode when the merging vehicle is stuck")
    sumo_args: tuple[StrictStr, ...] = Field((), description="extra SUMO command-line options")
    outputs: StrictBool = Field(
        False, description="SUMO's own outputs per episode (tripinfo, induction loops), parsed into "
        "env.sumo_outputs[seed]")
    output_dir: StrictStr | None = Field(
        None, description="folder of the per-episode output folders; null: a temporary folder")
    detector_offset: Number = Field(
        100.0, ge=0, description="induction loops this far past the last highway edge's start [m]")
    av_driver: AvDriver = Field(
        "env", description="env: the agents' actions drive the AVs; sumo: SUMO's models (a baseline)")

    @model_validator(mode="after")
    def _whole_steps(self) -> Self:
        _whole_multiple("decision_period", self.decision_period, "step_length", self.step_length, "SUMO steps")
        # An episode is a whole number of decisions: a shorter horizon would still run one, a fraction be cut.
        _whole_multiple("horizon", self.horizon, "decision_period", self.decision_period, "decision periods")
        return self


def _whole_multiple(key: str, value: float, unit_key: str, unit: float, units: str) -> None:
    """`key` is at least `unit_key` and a whole number of it, or a problem naming `key`."""
    if value < unit:
        raise _problem(f"must be at least {unit_key} ({unit:g} s), got {value:g} s", key)
    count = value / unit
    if abs(count - round(count)) > 1e-6:
        raise _problem(f"must be a whole number of {units} ({unit_key} = {unit:g} s), got {value:g} s = "
                       f"{count:.3g} {units}", key)


class SafetyConfig(_Section):
    """Surrogate safety measures beside crashes, as traffic-safety engineers count them, per episode of the episode
    env (not in demand mode). With `sim.outputs` (every evaluation) SUMO's SSM device rides in every vehicle and
    logs each conflict, an encounter in which a measure passes its threshold, with its worst value
    (`cosim.sumo.outputs.read_ssm`); hard braking is counted from the snapshots, so every episode has it
    (`cosim.environment.tracker`)."""

    ssm: StrictBool = Field(
        True, description="SUMO's SSM device with sim.outputs (about a third more time per episode); false: no "
        "conflicts are counted")
    ttc: Number = Field(1.5, gt=0, description="a time to collision below this is a conflict [s]")
    drac: Number = Field(
        3.4, gt=0, description="a deceleration rate to avoid a crash above this is a conflict (SUMO's default: 3) "
        "[m/s^2]")
    pet: Number = Field(2.0, gt=0, description="a post-encroachment time below this is a conflict [s]")
    hard_braking: Number = Field(
        4.0, gt=0, description="a vehicle whose speed falls by more than this times sim.decision_period from one "
        "decision to the next brakes hard; consecutive such periods are one event [m/s^2]")


class ScenarioConfig(_Section):
    """Where the vehicles start (cosim.sumo.scenario). Ranges [low, high] are drawn uniformly per episode seed.

    `placement: stream` (the merge dilemma): a dense stream of HVs and the AVs in the lane the merging vehicle
    must enter, each HV at its IDM equilibrium gap behind its leader at the stream's speed, led by a vehicle
    that drives at that speed; the stream reaches from `stream_head` back to `place_from`; one AV reaches the
    merge edge `guide_window` after the merging vehicle. `n_hvs` more HVs go on the other through lanes by the
    window rule. `placement: window` (free flow): `n_avs + n_hvs` vehicles spread over every through lane in
    [place_from, place_to] with front-to-front gaps in [min_gap, max_gap] and speeds in `speed_range`.
    """

    placement: Placement = Field("stream", description="stream | window (see the class docstring)")
    n_avs: Int = Field(4, gt=0, description="autonomous vehicles (the agents)")
    hv_density: Number | None = Field(
        16.0, ge=0, description="HVs placed by the window rule (stream: on the lanes beside the stream) per km and "
        "lane of the placement window, rounded; or n_hvs [veh/km/lane]")
    n_hvs: Int | None = Field(None, ge=0, description="... as a count (capped, with a warning, to what fits) [-]")
    place_share: ShareSpan | None = Field(
        (0.0, 1.0), description="placement window [from, to] as shares of the highway from its start to the "
        "acceleration lane's end; or place_from / place_to [-]")
    place_from: Number | None = Field(None, description="... along the highway from its first edge's start [m]")
    place_to: Number | None = Field(None, description="... upstream placement window end [m]")
    min_gap: Number = Field(
        30.0, gt=0, description="front-to-front spacing between window-placed vehicles in a lane, at least [m]")
    max_gap: Number = Field(60.0, description="... and at most [m]")
    speed_range_factor: NonNegativeSpan | None = Field(
        (0.69, 0.84), description="initial speeds of window-placed vehicles as factors of their lane's speed limit; "
        "or speed_range [-]")
    speed_range: NonNegativeSpan | None = Field(None, description="... in m/s [m/s]")
    merger_time: NonNegativeSpan | None = Field(
        (3.6, 5.4), description="the merging vehicle starts on the ramp this long (at its initial speed) before it "
        "reaches the acceleration lane; or merger_distance, or merger_pos [s]")
    merger_distance: NonNegativeSpan | None = Field(
        None, description="... this far before the acceleration lane, along the ramp [m]")
    merger_pos: NonNegativeSpan | None = Field(None, description="... at this position along the ramp's first edge [m]")
    merger_speed_factor: NonNegativeSpan | None = Field(
        (0.8, 1.0), description="initial speed of the merging vehicle as a factor of its lane's speed limit; or "
        "merger_speed [-]")
    merger_speed: NonNegativeSpan | None = Field(None, description="... in m/s [m/s]")
    merger_lane: Int | None = Field(
        None, ge=0, description="the ramp lane the merging vehicle starts in (0 = rightmost); null: the leftmost, "
        "the one nearest a highway it joins from the right [-]")
    inflow: Number = Field(0.0, ge=0, description="further HVs entering the highway start during the episode [veh/h]")
    stream_speed_factor: NonNegativeSpan | None = Field(
        (0.69, 0.81), description="the stream's speed as a factor of the speed limit of its lane on the merge edge; "
        "or stream_speed [-]")
    stream_speed: NonNegativeSpan | None = Field(None, description="... in m/s [m/s]")
    stream_head_share: Span | None = Field(
        (0.0, 0.67), description="its first vehicle, past the merge edge's start, as a share of the acceleration "
        "lane's length; or stream_head [-]")
    stream_head: Span | None = Field(None, description="... in metres [m]")
    stream_spacing: SpacingSpan = Field((1.0, 1.2), description="factor on each HV's equilibrium gap [-]")
    av_speed_offset_factor: Span | None = Field(
        (-0.03, 0.09), description="AVs' initial speed minus the stream's, as a factor of the stream lane's speed "
        "limit; or av_speed_offset [-]")
    av_speed_offset: Span | None = Field(None, description="... in m/s [m/s]")
    guide_window: Span = Field(
        (0.0, 3.0), description="one AV's arrival at the merge edge minus the merging vehicle's (both at their "
        "initial speeds) [s]")

    twins: ClassVar[tuple[Twins, ...]] = SCENARIO_TWINS

    @model_validator(mode="after")
    def _ordered_window(self) -> Self:
        if self.max_gap < self.min_gap:
            raise _problem(f"must be >= min_gap ({self.min_gap}), got {self.max_gap}", "max_gap")
        if (self.place_from is None) != (self.place_to is None):
            raise _problem("place_from and place_to go together (or use place_share)", "place_to")
        if self.place_from is not None and self.place_to <= self.place_from:
            raise _problem(f"must be greater than place_from ({self.place_from}), got {self.place_to}", "place_to")
        if self.place_share is not None and self.place_share[0] >= self.place_share[1]:
            raise _problem(f"expected [from, to] with from < to, got {list(self.place_share)}", "place_share")
        return self


class DriverConfig(_Section):
    """A vehicle type; HVs and the merging vehicle are driven by SUMO's models."""

    accel: Number = Field(2.6, description="[m/s^2]")
    decel: Number = Field(4.5, description="[m/s^2]")
    emergency_decel: Number = Field(9.0, description="[m/s^2]")
    max_speed_factor: Number | None = Field(
        1.0, gt=0, description="top speed (vType maxSpeed) as a factor of the highway's speed limit at the merge; "
        "or max_speed [-]")
    max_speed: Number | None = Field(None, gt=0, description="... in m/s [m/s]")
    length: Number = Field(5.0, description="[m]")
    width: Number = Field(1.8, description="[m]")
    min_gap: Number = Field(2.5, description="[m]")
    car_follow_model: StrictStr = Field("IDM", description="SUMO's carFollowModel")
    lane_change_model: Literal["LC2013", "SL2015"] = Field("LC2013", description="SUMO's laneChangeModel")
    speed_factor: NonNegativeSpan = Field(
        (0.95, 1.1), description="desired speed / speed limit, drawn per vehicle [-]")
    # IDM's T; 0.5-0.9 s is a dense stream (front-to-front about 1-1.5 s at its equilibrium gap), the low end of
    # real motorway traffic.
    tau_range: NonNegativeSpan = Field((0.5, 0.9), description="per-vehicle desired time headway, drawn uniformly [s]")
    sigma_range: NonNegativeSpan = Field(
        (0.0, 0.3), description="per-vehicle imperfection (Krauss models; IDM has none) [-]")
    lc_params: NumberMap = Field(
        default_factory=lambda: dict(NON_YIELDING),
        description="LC2013 / SL2015 parameters, e.g. {lcCooperative: 0.2}; the default never yields to the "
        "merging vehicle")

    twins: ClassVar[tuple[Twins, ...]] = DRIVER_TWINS

    @model_validator(mode="after")
    def _known_lc_params(self) -> Self:
        known = set().union(*LC_PARAMS.values())
        for name in self.lc_params:
            if name not in known:
                raise _problem(f"{name!r} is no lane-change parameter of SUMO's; {self.lane_change_model} reads "
                               f"{', '.join(sorted(LC_PARAMS[self.lane_change_model]))}", "lc_params")
        return self

    def ignored_lc_params(self) -> list[str]:
        """The `lc_params` names another model reads but the chosen one ignores (SUMO says nothing of them)."""
        return sorted(set(self.lc_params) - LC_PARAMS[self.lane_change_model])


class AVConfig(_Section):
    accel: Number = Field(3.0, gt=0, description="applied by the env: SUMO's own limits are off for AVs [m/s^2]")
    decel: Number = Field(5.0, gt=0, description="[m/s^2]")
    max_speed_factor: Number | None = Field(
        1.0, gt=0, description="the highest target speed as a factor of the highway's speed limit at the merge (also "
        "the speed reward's scale); or max_speed [-]")
    max_speed: Number | None = Field(None, gt=0, description="... in m/s [m/s]")
    speed_step_factor: Number | None = Field(
        0.075, gt=0, description="target-speed change of accelerate / decelerate as a factor of that limit; or "
        "speed_step [-]")
    speed_step: Number | None = Field(None, gt=0, description="... in m/s [m/s]")
    length: Number = Field(5.0, description="[m]")
    width: Number = Field(1.8, description="[m]")
    # The paper's setting is none: AVs may crash, and learning to avoid that is part of the task.
    shield: Shield = Field(
        "none", description="a safety layer under the policy: none, the AVs do what it says and may crash; sumo, "
        "SUMO's own safety checks bound them (cosim.sumo.session.AV_MODES): their speed never above the "
        "car-following model's safe speed, and a lane change only where it keeps the others' safe gaps (else the AV "
        "stays in its lane)")

    twins: ClassVar[tuple[Twins, ...]] = AV_TWINS


class ObservationConfig(_Section):
    twins: ClassVar[tuple[Twins, ...]] = OBSERVATION_TWINS
    preset: Preset = Field("default", description="one of OBSERVATION_PRESETS; the size keys below override it")
    channels: tuple[Channel, ...] = Field(CHANNELS, description="distinct channel names, in this order")
    # The sizes are null only until validation: a null takes the preset's value.
    frames: Int | None = Field(None, gt=0, description="stacked frames")
    height_px: Int | None = Field(None, gt=0, description="lateral pixels")
    width_px: Int | None = Field(None, gt=0, description="longitudinal pixels")
    length_m: Number | None = Field(None, gt=0, description="longitudinal extent of the window [m]")
    width_m: Number | None = Field(None, gt=0, description="lateral extent of the window [m]")
    ego_at: Number = Field(
        0.5, ge=0.0, le=1.0, description="ego's longitudinal place in the window, 0 = rear edge, 1 = front edge [-]")
    speed_scale_factor: Number | None = Field(
        0.45, gt=0, description="relative speed that moves a pixel value from 0.5 to 1, as a factor of the highway's "
        "speed limit at the merge; or speed_scale [-]")
    speed_scale: Number | None = Field(None, gt=0, description="... in m/s [m/s]")
    dtype: Literal["float32", "float16", "uint8"] = Field("float32", description="element type of the maps")

    @model_validator(mode="before")
    @classmethod
    def _preset_sizes(cls, data: Any) -> Any:
        if not isinstance(data, Mapping):
            return data
        name = data.get("preset", "default")
        preset = OBSERVATION_PRESETS.get(name) if isinstance(name, str) else None
        if preset is None:  # the Literal reports an unknown preset
            return data
        return {**data, **{k: v for k, v in preset.items() if data.get(k) is None}}

    @field_validator("channels")
    @classmethod
    def _distinct(cls, channels: tuple[str, ...]) -> tuple[str, ...]:
        if not channels or len(set(channels)) != len(channels):
            raise _problem(f"expected distinct names from {list(CHANNELS)}, got {list(channels)}")
        return channels

    @model_validator(mode="after")
    def _fits(self) -> Self:
        sizes = (self.frames, len(self.channels), self.height_px, self.width_px)
        values = math.prod(sizes)  # type: ignore[arg-type]  # the preset has set every size
        if values > MAX_OBSERVATION_VALUES:
            paper = OBSERVATION_PRESETS["paper"]
            raise _problem(
                f"frames x channels x height_px x width_px = {' x '.join(map(str, sizes))} = {values:,} values per "
                f"agent, more than {MAX_OBSERVATION_VALUES:,} ({MAX_OBSERVATION_VALUES * 4 // 2**20} MiB per agent "
                f"as float32; a worker keeps two stacks per AV, a training batch one per AV and decision step); "
                f"the paper preset has {paper['frames'] * len(CHANNELS) * paper['height_px'] * paper['width_px']:,}")
        return self


class DemandConfig(_Section):
    """Traffic over minutes instead of one episode (`cosim.sumo.demand`, `cosim.environment.demand_env`): vehicles
    enter the highway's start and the ramp's with exponential headways at the given demand, a share of the
    mainline ones AVs, from the start to the window's end; the first `warmup` seconds fill the net and are not
    measured. Capacities, for demands stated as shares: the highway's per lane from the HCM's basic freeway
    segments by its speed limit (2,200 pc/h/ln at 80 km/h or less to 2,400 at 113 km/h or more), the ramp's from
    the HCM's ramp roadways (1,800 pc/h at 32 km/h or less to 2,200 above 80 km/h); vehicles are taken as
    passenger cars."""

    twins: ClassVar[tuple[Twins, ...]] = DEMAND_TWINS
    enabled: StrictBool = Field(False, description="evaluate in demand mode (training stays on episodes)")
    mainline_share: Number | None = Field(
        0.6, ge=0, le=3, description="mainline demand per highway lane as a share of its capacity; or mainline_vph [-]")
    mainline_vph: Number | None = Field(None, ge=0, description="... per highway lane [veh/h]")
    ramp_share: Number | None = Field(
        0.4, ge=0, le=3, description="ramp demand as a share of the ramp's capacity (all its lanes); or ramp_vph [-]")
    ramp_vph: Number | None = Field(None, ge=0, description="... in vehicles per hour [veh/h]")
    av_penetration: Number | None = Field(
        0.1, ge=0, le=1, description="share of the mainline vehicles that are AVs (drawn per vehicle); or av_count [-]")
    av_count: Int | None = Field(None, ge=0, description="... as a number of AVs, spread over the mainline vehicles")
    warmup: Number = Field(120.0, ge=0, description="filling the net, not measured [s]")
    window: Number = Field(600.0, gt=0, description="the measurement window after the warm-up [s]")
    interval: Number = Field(
        30.0, gt=0, description="aggregation interval of the detectors (queue and flow-density samples) [s]")
    influence_area: Number = Field(
        457.0, gt=0, description="the merge influence area: from the acceleration lane's start this far downstream, "
        "the acceleration lane and the two right through lanes (HCM: 1,500 ft) [m]")
    max_avs_present: Int | None = Field(
        None, gt=0, description="observation slots, the most AVs present at once; null: estimated from the AV demand "
        "and the highway's length (an AV beyond it waits to enter) [-]")
    seeds: Int = Field(5, ge=1, description="evaluation runs (seeds) of the window, by default [-]")

    @model_validator(mode="after")
    def _window_of_intervals(self) -> Self:
        # The detectors' intervals start at 0: the window is measured by whole ones only where they align.
        for key in ("warmup", "window"):
            count = getattr(self, key) / self.interval
            if abs(count - round(count)) > 1e-6 or (key == "window" and count < 1 - 1e-6):
                raise _problem(f"must be a whole number of demand.interval ({self.interval:g} s, the detectors' "
                               f"aggregation), got {getattr(self, key):g} s", key)
        return self


class RewardConfig(_Section):
    phi: Annotated[Angle | tuple[Angle, ...], WrapValidator(_angles)] = Field(
        0.0, description="SVO angle, one for all AVs or one per AV: 0 egoistic, pi/4 altruistic, pi/2 fully [rad]")
    weights: NumberMap = Field(
        default_factory=dict,
        description="weights of the named utility terms (cosim.environment.reward.TERMS); unlisted terms keep "
        "their default")

    @field_validator("weights")
    @classmethod
    def _known_terms(cls, weights: Mapping[str, float]) -> Mapping[str, float]:
        unknown = sorted(set(weights) - set(_terms()))
        if unknown:
            raise _problem(f"unknown term; expected one of {sorted(_terms())}", unknown[0])
        return weights

    def weight(self, term: str) -> float:
        return float(self.weights.get(term, _terms()[term].weight))


def _terms() -> Mapping[str, Any]:
    # The reward module owns the term names (a term is registered beside its function); the config, which the
    # environment builds on, looks them up only when it judges weights, so neither module imports the other.
    from cosim.environment.reward import TERMS

    return TERMS


class TrainConfig(_Section):
    """Multi-agent actor-critic hyper-parameters. A "step" is one decision period of one env.

    One update: every worker plays one whole episode (seeded by the run's seed, the update and the worker);
    the network(s) then learn from the batch: every live AV's samples with `shared_policy` (the default),
    the learner AV's samples with per-AV networks (the paper's semi-sequential scheme). `a2c` takes one
    gradient step per batch (the paper's algorithm), `ppo` several epochs of clipped updates over it.
    Schedules run from the start value to the `_final` one over the run's progress: the larger of the
    fraction of `episodes` done and, with a `budget_min`, of the budget used.
    """

    algo: Algo = Field("a2c", description="a2c: one gradient step per batch; ppo: clipped epochs over it")
    shared_policy: StrictBool = Field(
        True, description="one network for all AVs; false: one per AV, trained semi-sequentially")
    workers: Int = Field(
        4, gt=0, description="rollout worker processes, one env (one SUMO) each; more than cores is fine")
    episodes: Int = Field(30000, gt=0, description="episodes to train for, in total over the run (resume continues)")
    budget_min: Number = Field(
        0.0, ge=0, description="wall-clock training time over the run (resumes included); 0: no limit [min]")
    gamma: Number = Field(0.95, ge=0, le=1, description="discount per decision step [-]")
    gae_lambda: Number = Field(0.95, ge=0, le=1, description="GAE lambda; 1 gives Monte-Carlo returns [-]")
    lr: Number = Field(2.5e-4, gt=0, description="learning rate at the start [-]")
    lr_final: Number | None = Field(
        None, ge=0, description="learning rate at the end of the run (linear schedule); null: lr throughout [-]")
    optimizer: OptimizerName = Field("adam", description="one of OPTIMIZER_NAMES")
    optimizer_eps: Number = Field(1e-5, gt=0, description="epsilon of Adam / RMSprop [-]")
    entropy_coef: Number = Field(0.01, ge=0, description="weight of the entropy bonus at the start [-]")
    entropy_final: Number | None = Field(
        None, ge=0, description="... at the end of the run (linear schedule); null: constant [-]")
    value_coef: Number = Field(0.5, ge=0, description="weight of the critic's squared error in the loss [-]")
    max_grad_norm: Number = Field(0.5, gt=0, description="global L2 norm the gradient of one step is clipped to [-]")
    normalize_advantage: StrictBool = Field(True, description="standardise advantages over each (mini)batch")
    value_norm: StrictBool = Field(
        True, description="the critic learns normalised returns (running mean and std of the targets)")
    ppo_epochs: Int = Field(4, gt=0, description="passes over each batch (ppo)")
    ppo_minibatches: Int = Field(4, gt=0, description="minibatches per pass (ppo)")
    clip_range: Number = Field(0.2, ge=0, le=1, description="PPO's ratio clip [-]")
    disseminate_every: Int = Field(
        10, gt=0, description="K: updates a learner AV trains before its weights are disseminated (per AV)")
    checkpoint_every: Int = Field(
        50, gt=0, description="updates between two checkpoints (one is also written at the end)")
    eval_every: Int = Field(
        0, ge=0, description="episodes between two validations: greedy episodes on the validation seeds "
        "(VALIDATION_SEED_START on, disjoint from training's and evaluation's), logged to validation.csv, the best "
        "kept as best.pt (agents.validation); 0: none")
    eval_episodes: Int = Field(
        200, gt=0, le=SEED_MAX - VALIDATION_SEED_START + 1,
        description="episodes of one validation (the same seeds each time)")
    log_every: Int = Field(1, gt=0, description="updates between two rows of the update log")
    log_every_s: Number = Field(
        30.0, ge=0, description="between two log lines when there is no terminal (no progress bar) [s]")
    seed: Seed = Field(
        0, description="seeds python, numpy, torch and the episodes; an episode's seed is drawn from (seed, update, "
        "worker) modulo EVAL_SEED_START, so training episodes stay below the evaluation seeds whatever this is")
    device: StrictStr = Field("cpu", description="torch device of the learner: cpu | cuda | cuda:N")
    precision: Precision = Field(
        "auto", description="forward passes of training: float32, bfloat16 (autocast; weights stay float32), or "
        "auto: bfloat16 where the hardware has it (CPUs whose lscpu flags include amx_bf16 or avx512_bf16, GPUs that "
        "support it), else float32; only float32 runs are reproducible bit for bit")
    feature_dim: Int = Field(512, gt=0, description="units of the feature extractor's FC layer (paper: 512)")
    head_hidden: Int = Field(256, gt=0, description="units of the actor's and critic's hidden FC layer (paper: 256)")
    max_restarts: Int = Field(100, ge=0, description="worker restarts tolerated over a run before it is stopped")
    step_timeout: Number = Field(
        60.0, gt=0, description="a worker silent this long is killed and restarted like a crashed one [s]")
    torch_threads: Int = Field(
        0, ge=0, description="torch intra-op threads of the learner; 0: one while the workers step, torch's default "
        "(all cores) for the update")
    # On by default: a masked action is one that would do nothing (a lane change toward no through lane, which also
    # draws the invalid_action penalty; accelerate at the top target speed, decelerate at 0), so the policy spends
    # no probability or exploration on it, as MARL_CAVs does. Runs trained before it existed trained without it.
    action_mask: StrictBool = Field(
        True, description="the policy samples only the actions the env's infos['action_mask'] allows, in acting and "
        "in the update (logits of masked actions -inf); recorded in the checkpoint, evaluation masks alike")

    @field_validator("device")
    @classmethod
    def _known_device(cls, device: str) -> str:
        problem = _device_problem(device)
        if problem:
            raise _problem(problem)
        return device


class EvaluateConfig(_Section):
    """The `evaluate:` section (all optional; command-line flags override)."""

    episodes: Int = Field(100, ge=1, description="evaluation episodes")
    seed: Seed = Field(
        EVAL_SEED_START, description="first evaluation seed (the episodes take seed .. seed + episodes - 1); "
        "training seeds stay below the default")
    greedy: StrictBool = Field(True, description="argmax actions; false: sampled from the policy")
    trajectories: Int = Field(3, ge=0, description="first episodes whose per-step trajectories are kept for plots")
    workers: Int = Field(1, ge=1, description="worker processes")
    step_timeout: Number = Field(
        60.0, gt=0, description="a worker that gives no step of its episode this long is replaced and the episode "
        "played again (with workers > 1) [s]")
    confidence: Number = Field(0.95, gt=0, lt=1, description="of the intervals in the summary [-]")

    @model_validator(mode="after")
    def _seeds_fit(self) -> Self:
        problem = _seed_problem(self.seed, self.episodes)
        if problem:
            raise _problem(problem, "seed")
        return self


class Config(_Section):
    net: NetConfig = Field(default_factory=NetConfig)
    sim: SimConfig = Field(default_factory=SimConfig)
    safety: SafetyConfig = Field(default_factory=SafetyConfig)
    scenario: ScenarioConfig = Field(default_factory=ScenarioConfig)
    hv: DriverConfig = Field(default_factory=DriverConfig)
    # A merger section given in a file starts from DriverConfig's defaults, not from these.
    merger: DriverConfig = Field(default_factory=lambda: DriverConfig(
        max_speed_factor=0.9, tau_range=(1.0, 1.0), sigma_range=(0.0, 0.0), speed_factor=(1.0, 1.0), lc_params={}))
    av: AVConfig = Field(default_factory=AVConfig)
    observation: ObservationConfig = Field(default_factory=ObservationConfig)
    reward: RewardConfig = Field(default_factory=RewardConfig)
    demand: DemandConfig = Field(default_factory=DemandConfig)
    train: TrainConfig = Field(default_factory=TrainConfig)
    evaluate: EvaluateConfig = Field(default_factory=EvaluateConfig)
    source: StrictStr | None = Field(None, exclude=True, description="the YAML file this came from, if any")

    @model_validator(mode="after")
    def _one_angle_per_av(self) -> Self:
        phi = self.reward.phi
        if isinstance(phi, tuple) and len(phi) != self.scenario.n_avs:
            raise _problem(f"a list needs one angle per AV ({self.scenario.n_avs}), got {len(phi)}", "reward.phi")
        return self

    @property
    def steps_per_decision(self) -> int:
        return max(1, round(self.sim.decision_period / self.sim.step_length))

    def phis(self) -> tuple[float, ...]:
        """The SVO angle of each AV [rad]."""
        phi = self.reward.phi
        return tuple(phi) if isinstance(phi, tuple) else (float(phi),) * self.scenario.n_avs

    def to_dict(self) -> dict[str, Any]:
        """A plain dict (YAML- and JSON-ready) that `load_config` turns back into an equal config (paths stay
        resolved). `train` and `evaluate` hold only the keys that were given: what config hashes and a resumed
        run's config comparison saw before these sections were typed (a run's config.yaml writes its whole
        `train` section itself)."""
        out = self.model_dump(mode="json")
        for name in ("train", "evaluate"):
            out[name] = getattr(self, name).model_dump(mode="json", exclude_unset=True)
        return out


_T = TypeVar("_T")


def parse_section(cls: type[_T], data: Any, where: str) -> _T:
    """Validate one section (a mapping; None: all defaults; an instance passes) into the model `cls`; problems
    raise `ConfigError` naming `where.key`."""
    if isinstance(data, cls):
        return data
    if not issubclass(cls, _Section):
        raise TypeError(f"parse_section: {cls!r} is not a config section model")
    return cls.model_validate({} if data is None else data, context={"where": where})


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
    parsed = _parse_overrides(overrides)
    # Where each overridden value came from, for the error lines: a string is the command line's --set, a
    # mapping's value was set in code (no input of the user's to name, and not the file's).
    given = ({key: "" for key in parsed} if isinstance(overrides, Mapping)
             else {item.partition("=")[0].strip(): f"--set {item.strip()}" for item in overrides or ()})
    for section in {key.partition(".")[0] for key in parsed}:  # overrides replace the files' twins (TWINS)
        if isinstance(data.get(section), dict):
            _clear_twins(section, data[section], {k.partition(".")[2]: v for k, v in parsed.items()
                                                  if k.partition(".")[0] == section})
    for key, value in parsed.items():
        _set_dotted(data, key, value)
    data["source"] = source
    return Config.model_validate(data, context={"source": source, "overrides": given})


def _plain(value: Any) -> Any:
    """A copy of nested mappings and sequences as dicts and lists, which overrides can then be set in."""
    if isinstance(value, Mapping):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    return value


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict[str, Any]:
    """A YAML config as a dict; `base: other.yaml` (relative to this file) is read first and this file's
    keys are merged over it, so experiments state only what differs."""
    if not path.is_file():
        raise ConfigError(f"config file {path}: not found")
    loaded = read_yaml(path)
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


def _merge(into: dict[str, Any], over: Mapping[str, Any], section: str = "") -> None:
    for key, value in over.items():
        if isinstance(value, Mapping) and isinstance(into.get(key), dict):
            if not section:  # a later layer's twin replaces the earlier layer's (TWINS)
                _clear_twins(key, into[key], value)
            _merge(into[key], value, key)
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
        try:
            parsed[key.strip()] = yaml.load(raw, Loader=_ConfigLoader)
        except yaml.YAMLError as exc:
            raise ConfigError(f"override {key.strip()}: {raw!r} is not a YAML value: "
                              f"{yaml_problem(exc, lines=False)}") from None
    return parsed


def read_yaml(path: Path) -> Any:
    """A YAML file's content (None for an empty one), read as config files are: UTF-8, no key given twice in a
    mapping; otherwise `ConfigError` naming the file and the position, on one line."""
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw[: exc.start].count(b"\n") + 1
        raise ConfigError(f"config file {path}: not UTF-8 text (byte 0x{raw[exc.start]:02x} on line {line})") from None
    try:
        return yaml.load(text, Loader=_ConfigLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(f"config file {path}: not valid YAML: {yaml_problem(exc)}") from None


class _ConfigLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping: YAML requires keys to be unique, and
    PyYAML would keep the last silently, losing the first (a whole `sim:` section, say) unseen."""

    def compose_document(self) -> yaml.Node:
        node = super().compose_document()
        _check_unique_keys(node, "", set())
        return node


def _check_unique_keys(node: yaml.Node, where: str, done: set[int]) -> None:
    if id(node) in done:  # an alias: checked where its anchor is (and a recursive one would never end)
        return
    done.add(id(node))
    children: list[tuple[str, yaml.Node]] = []
    if isinstance(node, yaml.MappingNode):
        first: dict[tuple[str, Any], yaml.Node] = {}
        for key, value in node.value:
            # `<<: *base` merges a mapping whose keys this one overrides on purpose.
            if key.tag != "tag:yaml.org,2002:merge" and isinstance(key, yaml.ScalarNode):
                dotted = f"{where}.{key.value}" if where else str(key.value)
                earlier = first.setdefault((key.tag, key.value), key)
                if earlier is not key:
                    raise yaml.constructor.ConstructorError(
                        problem=f"key {dotted} given twice (first on line {earlier.start_mark.line + 1})",
                        problem_mark=key.start_mark)
                children.append((dotted, value))
            else:
                children.append((where, value))
    elif isinstance(node, yaml.SequenceNode):
        children = [(f"{where}[{i}]", item) for i, item in enumerate(node.value)]
    for dotted, child in children:
        _check_unique_keys(child, dotted, done)


def yaml_problem(exc: yaml.YAMLError, lines: bool = True) -> str:
    """PyYAML's message on one line (its own spans several, with a caret under the spot): where, what, and
    what it was reading."""
    if not isinstance(exc, yaml.MarkedYAMLError) or exc.problem_mark is None:
        return " ".join(str(exc).split())

    def at(mark: Any) -> str:
        return f"line {mark.line + 1}, column {mark.column + 1}" if lines else f"column {mark.column + 1}"

    text = f"{at(exc.problem_mark)}: {exc.problem}"
    if exc.context:
        text += f" ({exc.context}" + (f" from {at(exc.context_mark)})" if exc.context_mark else ")")
    return text


def _set_dotted(data: dict[str, Any], key: str, value: Any) -> None:
    """Put an override into the raw dict. It replaces its key whole: `hv.lc_params={}` empties the mapping,
    where a `base:` file's mapping is merged into key by key."""
    node = data
    *parents, leaf = key.split(".")
    for i, part in enumerate(parents):
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"override {key}: {'.'.join(parents[: i + 1])} is not a section")
        node = child
    node[leaf] = value


# How a problem's message words what pydantic's error type asks for.
_EXPECTED = {
    "int_type": "an integer", "int_parsing": "an integer", "int_from_float": "an integer",
    "float_type": "a number", "float_parsing": "a number", "finite_number": "a finite number",
    "bool_type": "true or false", "bool_parsing": "true or false", "string_type": "a string",
    "tuple_type": "a list", "list_type": "a list", "dict_type": "a mapping", "mapping_type": "a mapping",
    "model_type": "a mapping", "model_attributes_type": "a mapping",
}
_BOUNDS = {"greater_than": (">", "gt"), "greater_than_equal": (">=", "ge"),
           "less_than": ("<", "lt"), "less_than_equal": ("<=", "le")}


def _error(exc: ValidationError, root: type[BaseModel], where: str, source: str | None = None,
           overrides: Mapping[str, str] = MappingProxyType({})) -> ConfigError:
    """One line per problem, naming the dotted key below `where` and where its value came from (`_origin`)."""
    lines = []
    for err in exc.errors(include_url=False):
        loc, kind, ctx = list(err["loc"]), err["type"], err.get("ctx") or {}
        value = err.get("input")
        got, prefix = _show(value), ""
        if kind == "cosim":
            if ctx.get("key"):
                loc.append(ctx["key"])
            text = ctx["message"]
        elif kind == "extra_forbidden":
            allowed = _keys_at(root, loc[:-1])
            prefix, text = "config key ", "unknown key" + (f"; allowed: {', '.join(allowed)}" if allowed else "")
        elif isinstance(value, float) and not math.isfinite(value):  # pydantic checks bounds first
            text = f"expected a finite number, got {got}"
        elif kind in _BOUNDS:
            op, bound = _BOUNDS[kind]
            text = f"must be {op} {_number(ctx[bound])}, got {got}"
        elif kind == "literal_error":
            text = f"expected {ctx['expected']}, got {got}"
        elif kind in _EXPECTED:
            text = f"expected {_EXPECTED[kind]}, got {got}"
        else:
            text = f"{err['msg']}, got {got}"
        key = _dotted(where, loc)
        lines.append(_origin(key, f"{prefix}{key or 'config'}: {text}", text, source, overrides))
    return ConfigError("\n".join(dict.fromkeys(lines)))


def _origin(key: str, line: str, text: str, source: str | None, overrides: Mapping[str, str]) -> str:
    """The problem `line` (`text` about `key`) prefixed with where the value came from: the `--set` that gave the
    key (its problem alone follows: `--set sim.horizon=-1: must be > 0, got -1`) or a section above it; nothing
    for a value set in code; else the file `source`, with the `--set`s inside a section whose own rule is broken
    (the values judged together came from both)."""
    owner = next((k for k in overrides if key == k or key.startswith((f"{k}.", f"{k}["))), None)
    if owner is not None:
        label = overrides[owner]
        return line if not label else f"{label}: {text}" if key == owner else f"{label}: {line}"
    inside = [label for k, label in overrides.items() if label and key and k.startswith(f"{key}.")]
    origin = " with ".join(filter(None, [source, ", ".join(inside)]))
    return f"{origin}: {line}" if origin else line


def _dotted(where: str, loc: Sequence[str | int]) -> str:
    path = where
    for part in loc:
        path += f"[{part}]" if isinstance(part, int) else f"{'.' if path else ''}{part}"
    return path


def _keys_at(root: type[BaseModel], loc: Sequence[str | int]) -> list[str]:
    """The keys of the section at `loc` below `root` (none where `loc` leads to no section model)."""
    model: Any = root
    for part in loc:
        field = model.model_fields.get(part) if isinstance(part, str) else None
        model = field.annotation if field is not None else None
        if not (isinstance(model, type) and issubclass(model, BaseModel)):
            return []
    return [k for k in model.model_fields if k != "source"]


def _number(bound: Any) -> str:
    # A bound on a float field comes back as a float: "> 0", not "> 0.0".
    return f"{bound:g}" if isinstance(bound, float) else str(bound)


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."
