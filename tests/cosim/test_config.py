"""Config loading: YAML, overrides, presets, typed sections, the schema, and clear errors for bad keys and values."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cosim.config import (
    MAX_OBSERVATION_VALUES,
    OBSERVATION_PRESETS,
    SEED_MAX,
    Config,
    EvaluateConfig,
    TrainConfig,
    check_seed,
    load_config,
)
from cosim.errors import ConfigError, SeedError

ROOT = Path(__file__).resolve().parents[2]


def test_default_yaml_resolves_net_relative_to_the_config() -> None:
    cfg = load_config(ROOT / "configs" / "default.yaml")
    assert Path(cfg.net.file) == ROOT / "sumo_net" / "dilemma" / "dilemma.net.xml"
    assert cfg.steps_per_decision == 10
    assert cfg.observation.frames == OBSERVATION_PRESETS["default"]["frames"]


def test_overrides_dict_and_cli_strings() -> None:
    a = load_config(ROOT / "configs" / "default.yaml", {"reward.phi": 0.785, "observation.preset": "paper"})
    b = load_config(ROOT / "configs" / "default.yaml", ["reward.phi=0.785", "observation.preset=paper"])
    assert a == b
    assert a.phis() == (0.785,) * a.scenario.n_avs
    assert (a.observation.frames, a.observation.height_px, a.observation.width_px) == (10, 64, 512)


def test_per_agent_phi_and_round_trip() -> None:
    cfg = load_config(None, {"scenario.n_avs": 2, "reward.phi": [0.0, math.pi / 2],
                             "reward.weights": {"collision": 9.0}, "train": {"lr": 0.1}})
    assert cfg.phis() == (0.0, math.pi / 2)
    assert load_config(cfg.to_dict()) == cfg


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"reward.phii": 1.0}, "reward.phii: unknown"),
        ({"scenario.n_avs": -1}, "scenario.n_avs: must be > 0"),
        ({"scenario.n_hvs": -3}, "scenario.n_hvs: must be >= 0"),
        ({"scenario.n_avs": 2.5}, "scenario.n_avs: expected an integer"),
        ({"sim.horizon": "long"}, "sim.horizon: expected a number"),
        ({"observation.preset": "huge"}, "observation.preset: expected 'default' or 'paper', got 'huge'"),
        ({"observation.channels": ["road", "cars"]}, "observation.channels"),
        ({"observation.dtype": "int64"}, "observation.dtype"),
        ({"reward.weights": {"speeed": 1.0}}, "reward.weights.speeed: unknown term"),
        ({"reward.phi": [0.1, 0.2]}, "reward.phi: a list needs one angle per AV"),
        ({"reward.phi": 45}, "reward.phi: expected an angle in radians"),
        ({"scenario.speed_range": [30, 20]}, "scenario.speed_range"),
        ({"hv.lane_change_model": "LC2025"}, "hv.lane_change_model"),
        ({"bogus": {"a": 1}}, "config key bogus: unknown"),
    ],
)
def test_bad_values_name_the_key(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("(", r"\(")):
        load_config(ROOT / "configs" / "default.yaml", overrides)


def test_bad_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("sim: [unclosed\n")
    with pytest.raises(ConfigError, match="not valid YAML"):
        load_config(bad)
    bad.write_text("- a\n- b\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(bad)
    with pytest.raises(ConfigError, match="KEY=VALUE"):
        load_config(None, ["reward.phi"])


def test_base_config_and_path_resolution(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    exp = tmp_path / "exp"
    exp.mkdir()
    (exp / "child.yaml").write_text(f"base: {ROOT / 'configs' / 'default.yaml'}\nreward:\n  phi: 0.5\n")
    cfg = load_config(exp / "child.yaml")
    assert cfg.reward.phi == 0.5 and cfg.scenario.n_avs == load_config(ROOT / "configs" / "default.yaml").scenario.n_avs
    assert Path(cfg.net.file) == ROOT / "sumo_net" / "dilemma" / "dilemma.net.xml"  # relative to the base's folder
    # A base of a base: free_flow names default.yaml and its own net, both relative to configs/.
    free_flow = load_config(ROOT / "configs" / "free_flow.yaml")
    assert Path(free_flow.net.file) == ROOT / "sumo_net" / "merge" / "merge.net.xml"
    (exp / "own.yaml").write_text("net:\n  file: nets/x.net.xml\n")
    assert load_config(exp / "own.yaml").net.file == str(exp / "nets" / "x.net.xml")
    monkeypatch.chdir(tmp_path)  # a command-line override is relative to the working directory
    assert load_config(exp / "own.yaml", ["net.file=y.net.xml"]).net.file == str(tmp_path / "y.net.xml")
    (exp / "loop.yaml").write_text("base: loop.yaml\n")
    with pytest.raises(ConfigError, match="includes itself"):
        load_config(exp / "loop.yaml")


def test_unknown_nested_key_names_the_path_and_the_allowed_keys() -> None:
    with pytest.raises(ConfigError) as caught:
        load_config(None, {"train": {"lrr": 0.1}})
    message = str(caught.value)
    assert message.startswith("config key train.lrr: unknown key; allowed: ")
    assert set(message.split("allowed: ")[1].split(", ")) == set(TrainConfig.model_fields)


def test_bound_violations_name_the_bound() -> None:
    for overrides, message in [({"train.gamma": 1.5}, "train.gamma: must be <= 1, got 1.5"),
                               ({"evaluate.workers": 0}, "evaluate.workers: must be >= 1, got 0"),
                               ({"sim.step_length": 0}, "sim.step_length: must be > 0, got 0"),
                               ({"train.algo": "dqn"}, "train.algo: expected 'a2c' or 'ppo', got 'dqn'")]:
        with pytest.raises(ConfigError) as caught:
            load_config(None, overrides)
        assert str(caught.value) == message


def test_every_problem_on_its_own_line_with_the_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(f"base: {ROOT / 'configs' / 'default.yaml'}\nscenario:\n  n_avs: 0\ntrain:\n  lr: fast\n"
                    "sim:\n  nope: 1\n")
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    lines = str(caught.value).splitlines()
    assert len(lines) == 3 and all(line.startswith(f"{path}: ") for line in lines)
    assert any("scenario.n_avs: must be > 0" in line for line in lines)
    assert any("train.lr: expected a number" in line for line in lines)


def test_a_bad_set_value_names_the_set_not_the_file(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text(f"base: {ROOT / 'configs' / 'default.yaml'}\nscenario:\n  n_avs: 0\n")
    with pytest.raises(ConfigError) as caught:
        load_config(path, ["sim.horizon=-1", "sim.nope=1", "reward.weights={speeed: 1}"])
    lines = {line.split(";")[0] for line in str(caught.value).splitlines()}
    assert lines == {f"{path}: scenario.n_avs: must be > 0, got 0",  # the file's own value names the file
                     "--set sim.horizon=-1: must be > 0, got -1",
                     "--set sim.nope=1: unknown key",
                     # A key below the one set is named after the --set.
                     "--set reward.weights={speeed: 1}: reward.weights.speeed: unknown term"}
    # A rule over a whole section judges values from both: both are named.
    with pytest.raises(ConfigError) as caught:
        load_config(path, ["scenario.n_avs=1", "observation.frames=100000", "observation.width_px=4096"])
    assert str(caught.value).startswith(f"{path} with --set observation.frames=100000, --set "
                                        "observation.width_px=4096: observation: frames x channels")
    # Values given in code (a dict) are the caller's: their key alone, never the file.
    with pytest.raises(ConfigError) as caught:
        load_config(path, {"scenario.n_avs": 1, "sim.horizon": -1})
    assert str(caught.value) == "sim.horizon: must be > 0, got -1"


def test_base_and_set_go_through_the_same_validation(tmp_path: Path) -> None:
    (tmp_path / "bad.yaml").write_text(f"base: {ROOT / 'configs' / 'default.yaml'}\nscenario:\n  n_avs: -1\n")
    (tmp_path / "child.yaml").write_text("base: bad.yaml\n")
    (tmp_path / "good.yaml").write_text(f"base: {ROOT / 'configs' / 'default.yaml'}\n")
    messages = []
    for path, overrides in [(tmp_path / "child.yaml", None), (tmp_path / "good.yaml", ["scenario.n_avs=-1"])]:
        with pytest.raises(ConfigError) as caught:
            load_config(path, overrides)
        messages.append(str(caught.value).removeprefix(f"{path}: ").removeprefix("--set scenario.n_avs=-1: "))
    assert messages[0] == "scenario.n_avs: must be > 0, got -1" and messages[1] == "must be > 0, got -1"


def test_train_and_evaluate_are_typed_sections() -> None:
    cfg = load_config(ROOT / "configs" / "smoke.yaml", ["evaluate.episodes=7", "train.lr=1"])
    assert isinstance(cfg.train, TrainConfig) and cfg.train.workers == 2 and cfg.train.lr == 1.0
    assert cfg.evaluate == EvaluateConfig(episodes=7) and cfg.evaluate.confidence == 0.95
    # to_dict keeps the keys given in these two sections, as before they were typed.
    assert cfg.to_dict()["evaluate"] == {"episodes": 7}
    assert set(cfg.to_dict()["train"]) == {"workers", "episodes", "checkpoint_every", "disseminate_every", "algo",
                                           "ppo_epochs", "ppo_minibatches", "gamma", "gae_lambda", "lr",
                                           "entropy_coef", "eval_every", "eval_episodes", "obs_norm",
                                           "egoistic_episodes"}
    assert load_config(cfg) == cfg


def test_json_schema_states_units_and_bounds() -> None:
    defs = Config.model_json_schema()["$defs"]
    units = {("SimConfig", "step_length"): "[s]", ("ScenarioConfig", "speed_range"): "[m/s]",
             ("AVConfig", "accel"): "[m/s^2]", ("RewardConfig", "phi"): "[rad]", ("TrainConfig", "budget_min"): "[min]",
             ("ScenarioConfig", "inflow"): "[veh/h]", ("SafetyConfig", "ttc"): "[s]",
             ("SafetyConfig", "drac"): "[m/s^2]", ("SafetyConfig", "pet"): "[s]",
             ("SafetyConfig", "hard_braking"): "[m/s^2]"}
    for (section, key), unit in units.items():
        assert defs[section]["properties"][key]["description"].endswith(unit), (section, key)
    assert defs["SimConfig"]["properties"]["step_length"]["exclusiveMinimum"] == 0
    assert defs["TrainConfig"]["properties"]["gamma"]["maximum"] == 1
    assert defs["TrainConfig"]["properties"]["algo"]["enum"] == ["a2c", "ppo"]
    assert defs["SafetyConfig"]["properties"]["ttc"]["exclusiveMinimum"] == 0
    with pytest.raises(ConfigError) as caught:
        load_config(None, {"safety.drac": -1, "safety.ttc_s": 1})
    assert str(caught.value).splitlines() == [
        "safety.drac: must be > 0, got -1",
        "config key safety.ttc_s: unknown key; allowed: ssm, ttc, drac, pet, hard_braking"]


@pytest.mark.parametrize("key", ["sim.seed", "train.seed", "evaluate.seed"])
def test_seed_keys_take_what_sumo_takes(key: str) -> None:
    episodes = {"evaluate.episodes": 1}  # evaluate.seed leaves room for its episodes' seeds
    assert load_config(None, {key: 0, **episodes}) is not None
    assert load_config(None, {key: SEED_MAX, **episodes}) is not None
    for bad in (-1, SEED_MAX + 1, 3_000_000_000):
        with pytest.raises(ConfigError) as caught:
            load_config(None, {key: bad, **episodes})
        assert str(caught.value) == (f"{key}: expected an integer in [0, 2147483647] (SUMO's --seed is a 32-bit "
                                     f"signed integer), got {bad}")
    with pytest.raises(ConfigError, match=f"{key}: expected an integer, got True"):
        load_config(None, {key: True})


def test_evaluation_seeds_fit_with_their_episodes() -> None:
    assert load_config(None, {"evaluate.seed": SEED_MAX - 99}).evaluate.seed == SEED_MAX - 99  # 100 episodes
    with pytest.raises(ConfigError, match=r"evaluate.seed: expected an integer in \[0, 2147483548\], so that the "
                                          r"seeds of all 100 episodes fit .*got 2147483549"):
        load_config(None, {"evaluate.seed": SEED_MAX - 98})


def test_check_seed_is_the_one_check_of_a_seed() -> None:
    for good in (0, 7, SEED_MAX, np.int64(7), np.uint32(7)):
        seed = check_seed("seed", good)
        assert seed == good and type(seed) is int
    for bad in (-1, SEED_MAX + 1, 3.0, "3", True, None, np.float64(3)):
        with pytest.raises(SeedError, match=r"^seed: expected an integer in \[0, 2147483647\]"):
            check_seed("seed", bad)
    assert issubclass(SeedError, ConfigError) and issubclass(SeedError, ValueError)
    assert check_seed("--seed", SEED_MAX - 9, 10) == SEED_MAX - 9
    with pytest.raises(SeedError, match=r"--seed: expected an integer in \[0, 2147483638\], so that the seeds of "
                                        r"all 10 episodes fit"):
        check_seed("--seed", SEED_MAX - 8, 10)
    seed_schema = Config.model_json_schema()["$defs"]["SimConfig"]["properties"]["seed"]
    assert (seed_schema["minimum"], seed_schema["maximum"]) == (0, SEED_MAX)


def test_a_key_given_twice_is_refused(tmp_path: Path) -> None:
    cases = {
        "sim:\n  seed: 1\nscenario:\n  n_avs: 2\nsim:\n  horizon: 5\n": "line 5, column 1: key sim given twice "
                                                                     "(first on line 1)",
        "sim:\n  seed: 1\n  seed: 2\n": "line 3, column 3: key sim.seed given twice (first on line 2)",
        "reward:\n  weights: {speed: 1, speed: 2}\n": "line 2, column 23: key reward.weights.speed given twice "
                                                     "(first on line 2)",
    }
    for text, message in cases.items():
        (tmp_path / "c.yaml").write_text(text)
        with pytest.raises(ConfigError) as caught:
            load_config(tmp_path / "c.yaml")
        assert str(caught.value) == f"config file {tmp_path / 'c.yaml'}: not valid YAML: {message}"
    # ... in a base file too, named as the file it is in.
    (tmp_path / "child.yaml").write_text("base: c.yaml\n")
    with pytest.raises(ConfigError, match=r"c\.yaml: not valid YAML: line 2, column 23: key reward.weights.speed"):
        load_config(tmp_path / "child.yaml")
    with pytest.raises(ConfigError, match=r"override reward.weights: .* key speed given twice"):
        load_config(None, ["reward.weights={speed: 1, speed: 2}"])
    # A YAML merge key is an override on purpose, not a key given twice.
    (tmp_path / "merge.yaml").write_text("sim: &s {seed: 1, horizon: 5}\nevaluate:\n  <<: {seed: 3, episodes: 2}\n"
                                         "  seed: 4\n")
    cfg = load_config(tmp_path / "merge.yaml")
    assert (cfg.sim.seed, cfg.evaluate.seed, cfg.evaluate.episodes) == (1, 4, 2)


def test_unreadable_yaml_is_one_line_naming_where(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"sim:\n  seed: 1\n# caf\xe9\n")
    with pytest.raises(ConfigError) as caught:
        load_config(bad)
    assert str(caught.value) == f"config file {bad}: not UTF-8 text (byte 0xe9 on line 3)"
    bad.write_text("sim:\n  seed: [1, 2\n")
    with pytest.raises(ConfigError) as caught:
        load_config(bad)
    assert str(caught.value) == (f"config file {bad}: not valid YAML: line 3, column 1: expected ',' or ']', but got "
                                 "'<stream end>' (while parsing a flow sequence from line 2, column 9)")
    with pytest.raises(ConfigError) as caught:
        load_config(None, ["reward.phi=[1,2"])
    assert str(caught.value) == ("override reward.phi: '[1,2' is not a YAML value: column 5: expected ',' or ']', "
                                 "but got '<stream end>' (while parsing a flow sequence from column 1)")


def test_observation_that_cannot_fit_is_refused_at_load() -> None:
    with pytest.raises(ConfigError) as caught:
        load_config(None, {"observation": {"frames": 100000, "height_px": 4096, "width_px": 4096}})
    assert str(caught.value).startswith(
        "observation: frames x channels x height_px x width_px = 100000 x 4 x 4096 x 4096 = 6,710,886,400,000 "
        f"values per agent, more than {MAX_OBSERVATION_VALUES:,} (64 MiB per agent as float32")
    # The paper's size, and well above it, stay allowed; the limit is the limit.
    paper = load_config(None, {"observation.preset": "paper"}).observation
    assert paper.frames * len(paper.channels) * paper.height_px * paper.width_px * 12 < MAX_OBSERVATION_VALUES
    load_config(None, {"observation": {"frames": 1, "channels": ["road"], "height_px": 4096, "width_px": 4096}})
    with pytest.raises(ConfigError, match="observation: frames x channels"):
        load_config(None, {"observation": {"frames": 1, "channels": ["road"], "height_px": 4096, "width_px": 4097}})


def test_inconsistent_timing_is_refused() -> None:
    for sim, message in [
        ({"step_length": 5, "decision_period": 5, "horizon": 1}, "sim.step_length: must be <= 1, got 5"),
        ({"decision_period": 5, "horizon": 1}, "sim.horizon: must be at least decision_period (5 s), got 1 s"),
        ({"horizon": 10.5}, "sim.horizon: must be a whole number of decision periods (decision_period = 1 s), got "
                            "10.5 s = 10.5 decision periods"),
    ]:
        with pytest.raises(ConfigError) as caught:
            load_config(None, {"sim": sim})
        assert str(caught.value) == message
    assert load_config(None, {"sim": {"step_length": 1, "decision_period": 2, "horizon": 4}}).sim.horizon == 4
    # These rules, the seeds' and the observation's keep every shipped experiment valid.
    for path in sorted((ROOT / "configs").glob("*.yaml")):
        load_config(path)


def test_config_does_not_import_the_reward_module() -> None:
    # The config types the terms' weights itself (RewardWeights); the reward module builds on it, not back.
    code = ("import sys, cosim.config; cosim.config.load_config(None, {'reward.weights': {'merge': 1.0}}); "
            "assert not [m for m in sys.modules if m.startswith(('cosim.environment', 'torch'))]")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_reward_weights_are_a_typed_section() -> None:
    defs = Config.model_json_schema()["$defs"]
    assert defs["RewardConfig"]["properties"]["weights"]["$ref"].endswith("/RewardWeights")
    weights = defs["RewardWeights"]["properties"]
    assert weights["merge"]["default"] == 10.0 and weights["collision"]["minimum"] == 0
    cfg = load_config(ROOT / "configs" / "default.yaml")
    assert (cfg.reward.weights.merge, cfg.reward.weights.speed, cfg.reward.weights.headway) == (50.0, 1.0, 1.0)
    # Only the weights given are written out, as a run's config.yaml always held them, so saved runs compare equal.
    assert cfg.to_dict()["reward"]["weights"] == {"merge": 50.0, "headway": 1.0}
    assert load_config(cfg.to_dict()).reward == cfg.reward
    with pytest.raises(ConfigError) as caught:
        load_config(None, {"reward.weights": {"merge": -1, "speeed": 1}})
    assert str(caught.value) == ("reward.weights.speeed: unknown term; the terms: speed, lane_change, invalid_action, "
                                 "accel, collision, merge, headway")
    with pytest.raises(ConfigError, match=r"^--set reward.weights.merge=-1: must be >= 0, got -1$"):
        load_config(None, ["reward.weights.merge=-1"])
