"""One resolved setting: an env resolves its config (and its demand) on the net once, at its start; resets, the
planners and the evaluation's records take that setting and resolve nothing again."""

from __future__ import annotations

import pytest

import cosim.sumo.setting as setting_module
from cosim.config import load_config
from cosim.environment.factory import parallel_env
from cosim.environment.flow_metrics import demand_setting
from cosim.sumo.setting import Setting

pytestmark = pytest.mark.sumo

DEMAND = {"demand.enabled": True, "demand.warmup": 30.0, "demand.window": 30.0, "demand.av_penetration": 0.3}


@pytest.fixture
def counted(monkeypatch: pytest.MonkeyPatch) -> dict[str, int]:
    """How often the config and the demand are resolved on a net, in this process."""
    calls = {"resolve": 0, "resolve_demand": 0}
    for name in calls:
        original = getattr(setting_module, name)

        def counting(*args: object, _name: str = name, _original: object = original) -> object:
            calls[_name] += 1
            return _original(*args)  # type: ignore[operator]

        monkeypatch.setattr(setting_module, name, counting)
    return calls


@pytest.mark.parametrize("demand", [False, True], ids=["episode", "demand"])
def test_an_env_resolves_once_and_its_resets_never_again(counted: dict[str, int], demand: bool) -> None:
    env = parallel_env("configs/default.yaml", DEMAND if demand else {})
    try:
        assert counted == {"resolve": 1, "resolve_demand": int(demand)}
        for seed in (1, 2):
            env.reset(seed=seed)
            env.step({a: 1 for a in env.agents})
        record = env.setting.record()
        assert counted == {"resolve": 1, "resolve_demand": int(demand)}
    finally:
        env.close()
    assert ("demand" in record) == demand and ("scenario" in record) != demand
    assert (env.setting.demand is not None) == demand and env.cfg is env.setting.config


def test_the_setting_is_resolved_on_its_net_and_its_demand_is_the_envs() -> None:
    raw = load_config("configs/default.yaml", DEMAND)
    on_net = Setting.of(raw)
    assert raw.scenario.stream_speed_factor is not None and on_net.config.scenario.stream_speed_factor is None
    assert on_net.config.av.max_speed_factor is None
    assert on_net.config.av.max_speed == pytest.approx(raw.av.max_speed_factor * on_net.net.speed_limit)
    figures = demand_setting(on_net)
    assert figures["mainline_vph"] == on_net.demand.mainline_vph and figures["interval"] == raw.demand.interval
