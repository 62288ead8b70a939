"""The config's sections: one frozen pydantic model per YAML section, and `Config`, the whole experiment.

Contract: each field declares its default, bounds and unit (`[unit]` ending its description) in one place, which
`Config.model_json_schema()` shows. Unknown keys are errors; missing keys keep the defaults. A section's
`model_validate` raises `ConfigError` (worded by `cosim.config.errors`). Cross-field rules: a decision is a whole
number of SUMO steps and the horizon a whole number of decisions; one agent's observation holds at most
`MAX_OBSERVATION_VALUES`; a net-relative key and its absolute twin (`TWINS`) are never both given. Every section,
`train:` and `evaluate:` and the reward terms' weights (`reward.weights`, one field per term of
`cosim.environment.reward.TERMS`) included, is typed here; nothing here imports torch or the environment, so
rollout workers and the CLI read it cheaply, and the environment builds on it, never the other way round.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, ClassVar, Literal, Self

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictStr,
    ValidationError,
    WrapValidator,
    field_validator,
    model_validator,
)

from cosim.config.errors import _error, _problem
from cosim.config.types import (
    CHANNELS,
    DEFAULT_NET,
    EVAL_SEED_START,
    LC_PARAMS,
    MAX_OBSERVATION_VALUES,
    NON_YIELDING,
    OBSERVATION_PRESETS,
    SEED_MAX,
    VALIDATION_SEED_START,
    Algo,
    Angle,
    AvDriver,
    Channel,
    Int,
    NonNegativeSpan,
    Number,
    NumberMap,
    OnCollision,
    OptimizerName,
    Placement,
    Precision,
    Preset,
    Seed,
    ShareSpan,
    Shield,
    SpacingSpan,
    Span,
    _angles,
    _device_problem,
    _resolve,
    _seed_problem,
)

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
    env and, in demand mode, the conflicts over the measurement window. With `sim.outputs` (every evaluation) SUMO's
    SSM device rides in every vehicle and logs each conflict, an encounter in which a measure passes its threshold,
    with its worst value (`cosim.sumo.outputs.read_ssm`); hard braking is counted from the episode env's snapshots,
    so every episode has it (`cosim.environment.tracker`)."""

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
    merger_alt_share: Number = Field(
        0.0, ge=0, le=1, description="share of the merging vehicles (per episode; under demand per ramp vehicle) "
        "drawn to drive the `merger_alt` type instead of `merger`, e.g. polite and impatient merging drivers in one "
        "training run [-]")
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

    @property
    def shape(self) -> tuple[int, int, int, int]:
        """One agent's stacked observation: (frames, channels, height_px, width_px)."""
        return (self.frames, len(self.channels), self.height_px, self.width_px)  # type: ignore[return-value]

    @model_validator(mode="after")
    def _fits(self) -> Self:
        sizes = self.shape  # the preset has set every size
        values = math.prod(sizes)
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
    # An AV's drive does not end where the simulated net does: ending its trajectory there as a terminal state
    # makes every step it stays worth more than leaving, as long as its reward per step is positive (a time limit
    # taken for a goal, Pardo et al. 2018).
    exit: Literal["truncated", "terminated"] = Field(
        "truncated", description="an AV that drives out of the net: truncated, its trajectory bootstrapped from the "
        "value of its last map, as at a segment's end; or terminated, worth nothing after it (training only)")

    @model_validator(mode="after")
    def _window_of_intervals(self) -> Self:
        # The detectors' intervals start at 0: the window is measured by whole ones only where they align.
        for key in ("warmup", "window"):
            count = getattr(self, key) / self.interval
            if abs(count - round(count)) > 1e-6 or (key == "window" and count < 1 - 1e-6):
                raise _problem(f"must be a whole number of demand.interval ({self.interval:g} s, the detectors' "
                               f"aggregation), got {getattr(self, key):g} s", key)
        return self


class RewardWeights(_Section):
    """The weight of each named utility term: one field per term of `cosim.environment.reward.TERMS`, which
    registers the term's function under the field's name, in this order (the order of summation). A term's value
    per vehicle and step is unweighted, its sign its own (a penalty's is negative), so a weight is >= 0; 0 turns
    the term off."""

    speed: Number = Field(1.0, ge=0, description="progress / (AV max speed x decision period), in [0, 1] [-]")
    lane_change: Number = Field(0.05, ge=0, description="-1 on the step an AV changes lane [-]")
    invalid_action: Number = Field(
        0.1, ge=0, description="-1 on the step an AV asks for a lane change toward no through lane [-]")
    accel: Number = Field(
        0.05, ge=0, description="-|speed change| / (AV accel x decision period), for every vehicle, so forcing "
        "humans to brake costs the social part [-]")
    # -5 as in the authors' follow-up code.
    collision: Number = Field(5.0, ge=0, description="-1 for a vehicle that crashed on the step [-]")
    # +10 as in the authors' follow-up code. With +2, letting the merging vehicle in lowered the guide AV's own
    # discounted return at phi = pi/4 (courteous 41.5 vs scripted 42.3 over 60 episodes); with +10 it raises it
    # (45.3 vs 42.8). Against SUMO-driven AVs, though, gap-opening ones earn no more with +10, so the default
    # scenario sets 50 (configs/default.yaml, results/calibration/merge_weight.md).
    merge: Number = Field(10.0, ge=0, description="+1 for the merging vehicle on the step it merges [-]")
    # MARL_CAVs prices a time gap under 1.2 s at 4 x this against a speed reward of up to 1 per step; the paper's
    # reward has no such term, so it is off unless asked for.
    headway: Number = Field(
        0.0, ge=0, description="min(0, ln(gap / (1.2 s x speed))) for an AV closer to its leader on its lane than "
        "1.2 s (MARL_CAVs' headway cost), per step [-]")

    @model_validator(mode="before")
    @classmethod
    def _known_terms(cls, data: Any) -> Any:
        # Worded as a term rather than pydantic's unknown key: the terms are the reward module's registry.
        if isinstance(data, Mapping):
            unknown = [str(key) for key in data if key not in cls.model_fields]
            if unknown:
                raise _problem(f"unknown term; the terms: {', '.join(cls.model_fields)}", unknown[0])
        return data


class RewardConfig(_Section):
    phi: Annotated[Angle | tuple[Angle, ...], WrapValidator(_angles)] = Field(
        0.0, description="SVO angle, one for all AVs or one per AV: 0 egoistic, pi/4 altruistic, pi/2 fully [rad]")
    weights: RewardWeights = Field(
        default_factory=RewardWeights, description="the utility terms' weights; unlisted terms keep their default")
    # The paper sums the others' utilities: with a fixed cast of vehicles (one merge) that is the same as their mean
    # up to a scale. In traffic the cast around an AV changes with what it does: a sum pays for every vehicle it
    # holds in view, a queue included, which the mean does not.
    social: Literal["sum", "mean"] = Field(
        "sum", description="how the others' utilities make the social part: sum (the paper's Eq. 3) or their mean")


class TrainConfig(_Section):
    """Multi-agent actor-critic hyper-parameters. A "step" is one decision period of one env.

    One update: every worker plays one whole episode (seeded by the run's seed, the update and the worker), or
    with `segments` (always under demand) `segment_steps` decisions of its continuing episodes (under demand an
    episode is one run); the network(s) then learn from the batch: every live AV's samples with `shared_policy`
    (the default), the learner AV's samples with per-AV networks (the paper's semi-sequential scheme). `a2c`
    takes one gradient step per batch (the paper's algorithm), `ppo` several epochs of clipped updates over it.
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
    init_from: StrictStr | None = Field(
        None, description="a new run starts from the networks of this policy file or run folder (in a YAML file: "
        "relative to that file), with a fresh optimizer; null: from scratch; `cosim train --init-from` overrides it, "
        "and a resume goes on from its own checkpoint")
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
    segments: StrictBool = Field(
        False, description="episodes: each update a segment of segment_steps decisions of every worker's continuing "
        "episodes (the next starts as one ends, none waits for the longest) instead of one whole episode per "
        "worker; under demand always")
    segment_steps: Int = Field(
        64, gt=0, description="under demand (or with segments): decisions of each worker's continuing run per "
        "update (CleanRL's num_steps); an AV that goes on past them is bootstrapped")
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
    shared_encoder: StrictBool = Field(
        True, description="one Conv3D encoder under the actor's and the critic's heads (the paper's network); false: "
        "each its own (MAPPO's default), twice the encoder's work per sample; on the default scenario it reached no "
        "safe policy sooner (docs/results.md)")
    central_critic: StrictBool = Field(
        False, description="the critic reads, beside an AV's own features, the mean of the features of every AV of "
        "its env at that decision (MAPPO's centralised value function); the actor still acts on its own map alone, "
        "so a trained policy plays as any other; needs shared_policy; false: each AV's critic on its own map, as in "
        "the paper")
    obs_norm: StrictBool = Field(
        False, description="standardise the network's input pixel by pixel by running statistics the learner keeps "
        "(as SB3's VecNormalize does for vector observations), saved with the weights; false: scaled to [0, 1] only, "
        "as in the paper and every run before the key (configs/default.yaml turns it on: a safe policy in fewer "
        "episodes, docs/results.md)")
    egoistic_episodes: Int = Field(
        0, ge=0, description="a curriculum: the first this many episodes train every AV on its own utility (the SVO "
        "reward at phi = 0), the rest on reward.phi's, with a fresh optimizer and value normaliser from the switch on, "
        "as a second run started from the first's policy (--init-from) would; inert where every AV's angle is 0, in a "
        "run that starts from a trained policy and under demand (measured on episodes only); 0: reward.phi's "
        "throughout [episodes]")
    feature_norm: StrictBool = Field(
        False, description="layer normalisation (Ba et al. 2016) of the encoder's features, between its FC layer and "
        "its ReLU, with a learned gain and bias per feature; false: none, as in the paper's network")
    policy_ema: Number = Field(
        0.0, ge=0, lt=1, description="decay per update of an exponential moving average of the network's weights "
        "(Polyak averaging, as Nikishin et al. 2018 and TensorFlow's ExponentialMovingAverage, its warm-up "
        "included): the policy validation plays and best.pt and policy.pt hold, while training acts and learns with "
        "the trained weights; 0: the trained weights throughout [-]")
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

    @model_validator(mode="after")
    def _central_critic_shared(self) -> Self:
        if self.central_critic and not self.shared_policy:
            raise _problem("a central critic pools the AVs' features of one network: it needs shared_policy: true "
                           "(or central_critic: false with one network per AV)", "central_critic")
        return self


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
    # Trained on one merging driver, AVs meet only that one; a second type, drawn per merging vehicle with
    # scenario.merger_alt_share, lets one run train on both (configs/mixed_merger.yaml).
    merger_alt: DriverConfig | None = Field(
        None, description="a second merging vehicle type (starts from DriverConfig's defaults, as merger: does)")
    av: AVConfig = Field(default_factory=AVConfig)
    observation: ObservationConfig = Field(default_factory=ObservationConfig)
    reward: RewardConfig = Field(default_factory=RewardConfig)
    demand: DemandConfig = Field(default_factory=DemandConfig)
    train: TrainConfig = Field(default_factory=TrainConfig)
    evaluate: EvaluateConfig = Field(default_factory=EvaluateConfig)
    source: StrictStr | None = Field(None, exclude=True, description="the YAML file this came from, if any")

    @model_validator(mode="after")
    def _alt_merger_given(self) -> Self:
        if self.scenario.merger_alt_share > 0 and self.merger_alt is None:
            raise _problem(f"{self.scenario.merger_alt_share} of the merging vehicles would drive the merger_alt "
                           "type, which is not given: add a merger_alt section (a vehicle type, as merger:) or set "
                           "the share to 0", "scenario.merger_alt_share")
        return self

    def merger_driver(self, alt: bool) -> DriverConfig:
        """The merging vehicle's type: `merger_alt` where it was drawn (`alt`), else `merger`."""
        return self.merger_alt if alt and self.merger_alt is not None else self.merger

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
        resolved). `train`, `evaluate` and `reward.weights` hold only the keys that were given: what config hashes
        and a resumed run's config comparison saw before these sections were typed (a run's config.yaml writes its
        whole `train` section itself)."""
        out = self.model_dump(mode="json")
        for name in ("train", "evaluate"):
            out[name] = getattr(self, name).model_dump(mode="json", exclude_unset=True)
        out["reward"]["weights"] = self.reward.weights.model_dump(mode="json", exclude_unset=True)
        return out
