"""The config's value types, constants and limits: what a single value may be, judged the same in every section.

Contract: the annotated types (`Int`, `Number`, `NumberMap`, `Angle`, `Seed`, the spans) reject what would
hide a mistake (a bool as a number, a float as an int, an infinite number, a span with low > high), each
problem worded by `cosim.config.errors`; the enumerated strings are a `Literal` (what a field accepts) and a
tuple (what other modules list or look up).

Seeds: `check_seed(name, seed, count)` is the one check of an episode seed (0 .. `SEED_MAX`, what SUMO's
`--seed` takes), behind the seed keys, the command-line seed flags and `MergeEnv.reset(seed=...)`. Training
episodes draw their seeds below `EVAL_SEED_START`, evaluation's default first seed; validation's start at
`VALIDATION_SEED_START`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Annotated, Any, Literal, get_args

from pydantic import (
    AfterValidator,
    AllowInfNan,
    BeforeValidator,
    Field,
    PlainSerializer,
    Strict,
    ValidationError,
    ValidatorFunctionWrapHandler,
)

from cosim.config.errors import _problem, _show
from cosim.errors import ConfigError, SeedError

# Demand levels as (mainline share of a lane's capacity, ramp share of the ramp's): light, near capacity (level of
# service E in the merge influence area), over capacity (F); shares of the HCM capacities, so the same on any net.
DEMAND_LEVELS: dict[str, tuple[float, float]] = {
    "light": (0.35, 0.25), "near capacity": (0.75, 0.45), "over capacity": (0.9, 0.6)}
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
DEFAULT_NET = Path(__file__).resolve().parents[2] / "sumo_net" / "dilemma" / "dilemma.net.xml"
# The experiment a command runs without --config, found from any working directory.
DEFAULT_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "default.yaml"
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



def _resolve(path: str, base: Path) -> Path:
    p = Path(path).expanduser()
    return p if p.is_absolute() else (base / p).resolve()
