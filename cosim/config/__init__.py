"""Typed experiment config: frozen pydantic models loaded from YAML, validated once at load.

Contract: `load_config(path_or_dict_or_Config, overrides)` returns a frozen `Config` or raises `ConfigError` with
one line per problem, naming the dotted key, what is allowed and where the value came from (the `--set` or the
file). Unknown keys are errors; missing keys keep the defaults; each field declares its default, bounds and unit
in one place, which `Config.model_json_schema()` shows. `check_seed` is the one check of an episode seed. The
package imports neither torch nor the environment, so rollout workers and the CLI read it cheaply.

Modules, each importing only those before it: `errors` (how a problem is worded) -> `types` (value types,
constants, limits, seeds) -> `sections` (the section models, `Config`, twins) -> `loading` (YAML files, `base:`
chains, `--set` overrides). Import from `cosim.config`: every name other modules use is re-exported here.
"""

from cosim.config.errors import (
    yaml_problem,
)
from cosim.config.loading import (
    load_config,
    parse_section,
    read_yaml,
)
from cosim.config.sections import (
    AV_TWINS,
    DEMAND_TWINS,
    DRIVER_TWINS,
    OBSERVATION_TWINS,
    SCENARIO_TWINS,
    TWINS,
    AVConfig,
    Config,
    DemandConfig,
    DriverConfig,
    EvaluateConfig,
    NetConfig,
    ObservationConfig,
    RewardConfig,
    RewardWeights,
    SafetyConfig,
    ScenarioConfig,
    SimConfig,
    TrainConfig,
    Twins,
)
from cosim.config.types import (
    ALGOS,
    AV_DRIVERS,
    CHANNELS,
    DEFAULT_CONFIG,
    DEFAULT_NET,
    DEMAND_LEVELS,
    EVAL_SEED_START,
    LC_PARAMS,
    MAX_OBSERVATION_VALUES,
    NON_YIELDING,
    OBSERVATION_PRESETS,
    ON_COLLISION,
    OPTIMIZER_NAMES,
    PLACEMENTS,
    PRECISIONS,
    SEED_MAX,
    SHIELDS,
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
    check_device,
    check_seed,
)
