"""The scenario's net-relative keys, resolved on one net into absolute units.

Contract: `resolve(cfg, net)` returns a `Resolved` (`cosim.sumo.setting.Setting.of(cfg)` loads the config's own net
and resolves on it, once for a run): `config`, the same experiment with every net-relative key
of `cosim.config.TWINS` replaced by its absolute twin for this net, and `notes`, one line per value the net
cannot take, naming the key, what was asked and what it became (capped, never a SUMO error). Speeds are
factors of speed limits: the highway's where the merge is (`Net.speed_limit`: the AVs' top speed and speed
step, the drivers' top speeds, the observation's speed scale, the stream and the AVs' offset from it) and
the ramp's (`Net.ramp_speed_limit`: the merging vehicle); lengths are shares of the net's (the placement
window of the highway up to the acceleration lane's end, the stream's head of the acceleration lane); HV
counts follow a density per km and lane of the placement window, checked against the lanes there are. Two
quantities are resolved per vehicle by the planner (cosim.sumo.scenario), whose values depend on the draws:
window speeds (`speed_range_factor`, of each vehicle's own lane) and the merging vehicle's start
(`merger_time`, `merger_distance` or `merger_pos`; capped at the ramp's start). Everything downstream of the
env (the planner, control, reward, observation, the hand-written policies) reads the resolved config.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from cosim.config import Config, DriverConfig
from cosim.sumo.net import Net


@dataclass(frozen=True)
class Resolved:
    config: Config
    notes: tuple[str, ...]  # one line per capped value, naming its key


def _span(factor: tuple[float, float], scale: float) -> tuple[float, float]:
    return factor[0] * scale, factor[1] * scale


def window_lanes(cfg: Config, net: Net) -> int:
    """Lanes the window rule places HVs on: every through lane (placement window), or those beside the stream."""
    n = min(len(net.through_lanes(e)) for e in net.desc.highway)
    return n if cfg.scenario.placement == "window" else max(n - 1, 0)


def window_fit(length: float, lanes: int, min_gap: float, max_gap: float) -> int:
    """Vehicles the window rule places for sure on `lanes` lanes of `length` [m]: slots are `min_gap` to
    `max_gap` apart, the first within `min_gap` of the window's start."""
    return lanes * (int(max(length - min_gap, 0.0) // max_gap) + 1) if length >= 0 else 0


def resolve(cfg: Config, net: Net) -> Resolved:
    notes: list[str] = []
    sc, limit = cfg.scenario, net.speed_limit
    where = f"on {net.road.net_file.name}"

    def factor_or(value: Any, factor: Any, scale: float) -> Any:
        return value if factor is None else (_span(factor, scale) if isinstance(factor, tuple) else factor * scale)

    av = cfg.av.model_copy(update={
        "max_speed": factor_or(cfg.av.max_speed, cfg.av.max_speed_factor, limit), "max_speed_factor": None,
        "speed_step": factor_or(cfg.av.speed_step, cfg.av.speed_step_factor, limit), "speed_step_factor": None})
    def top_speed(d: DriverConfig) -> DriverConfig:
        return d.model_copy(update={"max_speed": factor_or(d.max_speed, d.max_speed_factor, limit),
                                    "max_speed_factor": None})

    hv, merger = top_speed(cfg.hv), top_speed(cfg.merger)
    merger_alt = None if cfg.merger_alt is None else top_speed(cfg.merger_alt)
    mergers = [merger, merger_alt] if merger_alt is not None and sc.merger_alt_share > 0 else [merger]
    obs = cfg.observation.model_copy(update={
        "speed_scale": factor_or(cfg.observation.speed_scale, cfg.observation.speed_scale_factor, limit),
        "speed_scale_factor": None})

    up: dict[str, Any] = {}
    up["stream_speed"] = stream = factor_or(sc.stream_speed, sc.stream_speed_factor, limit)
    if stream[1] > limit:
        notes.append(f"scenario.stream_speed: up to {stream[1]:.1f} m/s, above the {limit:.1f} m/s speed limit of "
                     f"the stream's lane {where}: its vehicles start at no more than the limit")
    up["av_speed_offset"] = factor_or(sc.av_speed_offset, sc.av_speed_offset_factor, limit)
    up["stream_head"] = factor_or(sc.stream_head, sc.stream_head_share, net.accel_length)
    if sc.merger_speed is not None:
        top = min(min(net.ramp_speed_limit * min(d.speed_factor), d.max_speed) for d in mergers)
        if sc.merger_speed[1] > top:
            capped = (min(sc.merger_speed[0], top), top)
            notes.append(f"scenario.merger_speed: {list(sc.merger_speed)} m/s is above what the merging vehicle may "
                         f"start at on the ramp {where} ({top:.1f} m/s: its speed limit x merger.speed_factor, or "
                         f"merger.max_speed): capped to [{capped[0]:.1f}, {capped[1]:.1f}]")
            up["merger_speed"] = capped
    else:
        up["merger_speed"] = _span(sc.merger_speed_factor, net.ramp_speed_limit)
    _merger_start(cfg, net, up, notes, where)
    _merger_lane(cfg, net, up, notes, where)
    _window(cfg, net, up, notes, where)
    for relative in ("stream_speed_factor", "av_speed_offset_factor", "stream_head_share", "merger_speed_factor",
                     "place_share", "hv_density"):
        up[relative] = None
    scenario = sc.model_copy(update=up)
    config = cfg.model_copy(update={"av": av, "hv": hv, "merger": merger, "merger_alt": merger_alt,
                                    "observation": obs, "scenario": scenario})
    return Resolved(config, tuple(notes))


def _merger_start(cfg: Config, net: Net, up: dict[str, Any], notes: list[str], where: str) -> None:
    sc = cfg.scenario
    first = net.desc.ramp[0]
    ramp = net.chainage.merge_start - net.ramp_offsets[first]  # [m] from the ramp's start to the acceleration lane
    if sc.merger_pos is not None:
        length = net.road.edge_length(first)
        if sc.merger_pos[1] >= length:
            capped = (min(sc.merger_pos[0], length - 1.0), length - 1.0)
            notes.append(f"scenario.merger_pos: {list(sc.merger_pos)} m lies beyond the ramp's first edge {first!r} "
                         f"{where} (0 to {length:.1f} m): capped to [{capped[0]:.1f}, {capped[1]:.1f}]")
            up["merger_pos"] = capped
        return
    if sc.merger_distance is not None:
        far, what = sc.merger_distance[1], f"scenario.merger_distance: up to {sc.merger_distance[1]:.0f} m"
    else:
        speed = up.get("merger_speed") or sc.merger_speed
        far = sc.merger_time[1] * speed[1]
        what = f"scenario.merger_time: up to {sc.merger_time[1]:g} s at up to {speed[1]:.1f} m/s is {far:.0f} m"
    if far > ramp:
        notes.append(f"{what}, more than the ramp's {ramp:.0f} m before the acceleration lane {where}: the merging "
                     "vehicle starts no further up than the ramp's start")


def _merger_lane(cfg: Config, net: Net, up: dict[str, Any], notes: list[str], where: str) -> None:
    lanes = min(net.road.num_lanes(e) for e in net.desc.ramp)
    lane = cfg.scenario.merger_lane
    if lane is not None and lane >= lanes:
        notes.append(f"scenario.merger_lane: lane {lane} does not exist on every ramp edge {where} (lanes "
                     f"0..{lanes - 1} do): the merging vehicle starts in lane {lanes - 1}")
        up["merger_lane"] = lanes - 1


def _window(cfg: Config, net: Net, up: dict[str, Any], notes: list[str], where: str) -> None:
    """The placement window [m] and the HVs it holds."""
    sc = cfg.scenario
    if sc.place_share is not None:
        lo, hi = _span(sc.place_share, net.chainage.merge_end)
        lo, hi = max(lo, 0.0), min(hi, net.highway_length)
    else:
        lo, hi = max(sc.place_from, 0.0), min(sc.place_to, net.highway_length)
        if (lo, hi) != (sc.place_from, sc.place_to):
            notes.append(f"scenario.place_from / place_to: [{sc.place_from:g}, {sc.place_to:g}] m reaches off the "
                         f"highway {where} ([0, {net.highway_length:.1f}] m): capped to [{lo:.1f}, {hi:.1f}]")
    up["place_from"], up["place_to"] = lo, hi
    lanes = window_lanes(cfg, net)
    fit = window_fit(hi - lo, lanes, sc.min_gap, sc.max_gap)
    if sc.placement == "window":
        fit = max(fit - sc.n_avs, 0)  # the AVs take window slots too
    if sc.n_hvs is not None:
        asked, key = sc.n_hvs, "scenario.n_hvs"
    else:
        asked, key = round(sc.hv_density * lanes * (hi - lo) / 1000.0), "scenario.hv_density"
    up["n_hvs"] = min(asked, fit)
    if asked > fit:
        what = f"{asked} HVs" if key.endswith("n_hvs") else f"{sc.hv_density:g} veh/km/lane ({asked} HVs)"
        notes.append(f"{key}: {what} do not fit {where}: {fit} fit for sure on its {lanes} lane(s) of the "
                     f"{hi - lo:.0f} m placement window{' beside the stream' if sc.placement == 'stream' else ''} "
                     f"with min_gap {sc.min_gap:g} m and max_gap {sc.max_gap:g} m: placing {fit}")


def scenario_lines(cfg: Config, net: Net) -> list[str]:
    """A resolved config's scenario on `net`, in words (a few lines)."""
    sc = cfg.scenario

    def rng(pair: tuple[float, float], unit: str, fmt: str = ".1f") -> str:
        return f"{pair[0]:{fmt}}-{pair[1]:{fmt}} {unit}" if pair[0] != pair[1] else f"{pair[0]:{fmt}} {unit}"

    if sc.placement == "stream":
        lane = net.through_lanes(net.desc.merge_edge)[net.target_rank()]
        head = rng(sc.stream_head, "m", ".0f")
        where = (f"a stream of HVs and {sc.n_avs} AVs in the lane the merging vehicle enters (lane {lane} of "
                 f"{net.desc.merge_edge!r}) at {rng(sc.stream_speed, 'm/s')}, its head {head} past the merge edge's "
                 f"start; {sc.n_hvs} HVs beside it in [{sc.place_from:.0f}, {sc.place_to:.0f}] m")
    else:
        speeds = (rng(sc.speed_range, "m/s") if sc.speed_range is not None
                  else rng(sc.speed_range_factor, "x the lane's limit", ".2f"))
        where = (f"{sc.n_avs} AVs and {sc.n_hvs} HVs over {window_lanes(cfg, net)} lanes in [{sc.place_from:.0f}, "
                 f"{sc.place_to:.0f}] m at {speeds}")
    if sc.merger_pos is not None:
        start = f"at {rng(sc.merger_pos, 'm', '.0f')} along {net.desc.ramp[0]!r}"
    elif sc.merger_distance is not None:
        start = f"{rng(sc.merger_distance, 'm', '.0f')} before the acceleration lane"
    else:
        start = f"{rng(sc.merger_time, 's')} before the acceleration lane"
    return [where, f"the merging vehicle starts {start} at {rng(sc.merger_speed, 'm/s')}", *driver_lines(cfg)]


def driver_lines(cfg: Config) -> list[str]:
    """How the AVs and HVs drive, in words: the part of `scenario_lines` that a demand run shares."""
    return [f"AVs: top speed {cfg.av.max_speed:.1f} m/s, speed step {cfg.av.speed_step:.2f} m/s; observation speed "
            f"scale {cfg.observation.speed_scale:.1f} m/s; HVs' top speed {cfg.hv.max_speed:.1f} m/s",
            *merger_lines(cfg), SHIELD_LINES[cfg.av.shield]]


def merger_lines(cfg: Config) -> list[str]:
    """The merging drivers' mix, where there is one."""
    share, alt = cfg.scenario.merger_alt_share, cfg.merger_alt
    if share <= 0 or alt is None:
        return []
    return [f"merging vehicles: {1 - share:.0%} merger ({cfg.merger.lane_change_model} {dict(cfg.merger.lc_params)}), "
            f"{share:.0%} merger_alt ({alt.lane_change_model} {dict(alt.lc_params)}), drawn per vehicle"]


# What each `av.shield` means for the AVs the env drives, in the reports' words.
SHIELD_LINES = {"none": "safety layer: none, the AVs do what the policy says and may crash (the paper's setting)",
                "sumo": "safety layer: sumo, SUMO's safe speed and safe-gap lane-change checks bound the AVs' actions"}
