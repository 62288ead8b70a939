"""The `cosim` command: every subcommand's options and what it runs, here and nowhere else.

Contract: each subcommand is a pair of functions below, `_NAME_arguments(parser)` and `_NAME(args) -> int`,
listed in `COMMANDS`; they parse and check the command line and call the library (`sumo_net.build`,
`cosim.environment`, `cosim.bench`, `agents.train`, `agents.sweep`, `cosim.evaluation`). This module is the
composition root: the only place in `cosim` that reaches into `agents`, and only inside the commands that need
it, so `cosim build-net` never loads torch. A `CosimError` (bad config, bad net, SUMO failure) or an OS error
(a folder that cannot be written, a file where a folder should be) is printed as one line, exit status 2, not
a traceback. Ctrl-C (SIGINT) and SIGTERM stop a command cleanly (a training run writes its checkpoint first)
with exit status 130.
"""

from __future__ import annotations

import argparse
import logging
import shlex
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from tqdm import tqdm
from tqdm.contrib.logging import logging_redirect_tqdm

from cosim.config import DEFAULT_CONFIG, EVAL_SEED_START, check_seed
from cosim.errors import ConfigError, CosimError, check_at_least
from cosim.files import atomic_copy

log = logging.getLogger("cosim")


# -- shared options ------------------------------------------------------------------------------------
def add_config_arguments(parser: argparse.ArgumentParser, default: str | Path | None = DEFAULT_CONFIG,
                         net: bool = True) -> None:
    """The config options every env-using command shares: --config, --set and (with `net`) --net."""
    parser.add_argument("--config", default=default, help="experiment YAML (default: %(default)s)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                        help="override a config key, e.g. --set reward.phi=0.785 (repeatable); a path given here "
                             "(net.file) is relative to the working directory, one in a YAML file to that file")
    if net:
        parser.add_argument("--net", type=Path, default=None, metavar="NET.net.xml",
                            help="run on this SUMO net instead of the config's (its description YAML is read from "
                                 "beside it, else inferred; the scenario follows the net: cosim check-net NET)")


def config_overrides(args: argparse.Namespace) -> list[str]:
    """The command line's config overrides: every --set, then --net as `net.file` (with its description found
    beside it or inferred), checked to exist."""
    overrides = list(args.overrides)
    net = getattr(args, "net", None)
    if net is not None:
        if not net.is_file():
            raise ConfigError(f"--net {net}: not found (expected a SUMO .net.xml)")
        overrides += [f"net.file={net.resolve()}", "net.description=null"]
    return overrides


def _backend_arguments(parser: argparse.ArgumentParser) -> None:
    from agents.rollout import BACKENDS

    parser.add_argument("--backend", choices=BACKENDS, default="local",
                        help="rollout workers as local processes (default) or as Ray actors (pip install -e "
                             "\".[ray]\"); a training run's learner stays in its own process, a sweep's runs are "
                             "Ray tasks")
    parser.add_argument("--ray-address", default=None, metavar="auto|HOST:PORT",
                        help="with --backend ray: the Ray cluster to join (auto: the one `ray start` runs here); "
                             "default: start a local Ray")


def _positive(args: argparse.Namespace, *names: str, least: int = 1) -> None:
    for name in names:
        check_at_least(f"--{name}", getattr(args, name.replace("-", "_")), least)


# -- build-net -----------------------------------------------------------------------------------------
# build-net's geometry flags: (flag, type, unit, help); each is a MergeGeometry field of the same name.
GEOMETRY_FLAGS: tuple[tuple[str, type, str, str], ...] = (
    ("lanes", int, "", "through lanes of the highway"),
    ("upstream-length", float, "[m] ", "before the merge"),
    ("accel-length", float, "[m] ", "acceleration lane"),
    ("ramp-length", float, "[m] ", "on-ramp"),
    ("downstream-length", float, "[m] ", "after the merge"),
    ("highway-speed", float, "[m/s] ", "highway speed limit"),
    ("ramp-speed", float, "[m/s] ", "ramp speed limit"),
    ("lane-width", float, "[m] ", "lane width"),
    ("ramp-lanes", int, "", "lanes of the ramp (and acceleration lanes)"),
    ("upstream-edges", int, "", "edges the approach is split into"),
    ("ramp-edges", int, "", "edges the ramp is split into"),
    ("downstream-edges", int, "", "edges the road after the merge is split into"),
    ("curve-radius", float, "[m] ", "the highway bends left on this radius (0: straight)"),
)


def _build_net_arguments(p: argparse.ArgumentParser) -> None:
    from sumo_net.build import MergeGeometry
    from sumo_net.shapes import SHAPES

    d = MergeGeometry()
    p.add_argument("--shape", choices=sorted(SHAPES), default=None,
                   help="start from one of the usual shapes (sumo_net/shapes.py); the flags below, where given, "
                        "replace its values")
    # Defaults are None so that a flag given beside --shape is told from one left out; the built-in value
    # (MergeGeometry's) stands in the help.
    for flag, kind, unit, text in GEOMETRY_FLAGS:
        key = flag.replace("-", "_")
        p.add_argument(f"--{flag}", type=kind, default=None,
                       help=f"{unit}{text} (default: the shape's, or {getattr(d, key):g})")
    p.add_argument("--lane-drop", action="store_true", default=None,
                   help="the leftmost lane ends after the first edge past the merge (needs --downstream-edges 2)")
    p.add_argument("--name", default=None, help="file stem of the outputs (default: merge, or the shape's name)")
    p.add_argument("--out", type=Path, required=True, help="output folder")


def _build_net(args: argparse.Namespace) -> int:
    from sumo_net.build import build_merge_net
    from sumo_net.shapes import SHAPES

    name = args.name or args.shape or "merge"
    geometry = dict(SHAPES[args.shape]) if args.shape is not None else {}
    keys = [flag.replace("-", "_") for flag, *_ in GEOMETRY_FLAGS] + ["lane_drop"]
    geometry.update({key: getattr(args, key) for key in keys if getattr(args, key) is not None})
    net_file = build_merge_net(args.out, name=name, **geometry)  # MergeGeometry checks every value
    log.info("wrote %s and %s", net_file, net_file.with_name(f"{name}.yaml"))
    return 0


# -- run-scenario --------------------------------------------------------------------------------------
def _run_scenario_arguments(parser: argparse.ArgumentParser) -> None:
    from cosim.environment.policies import POLICIES

    add_config_arguments(parser)
    parser.add_argument("--episodes", type=int, default=3, help="episodes to run (default: %(default)s)")
    parser.add_argument("--policy", choices=sorted(POLICIES), action="append",
                        help="policy to run, repeatable (default: scripted and random)")
    parser.add_argument("--seed", type=int, default=None, help="first episode's seed (default: config)")
    parser.add_argument("--save-routes", type=Path, default=None, metavar="DIR",
                        help="keep each episode's SUMO route file (vTypes, routes, vehicles) here, e.g. to "
                             "open it with sumo-gui -n NET -r DIR/episode_SEED.rou.xml")


def _run_scenario(args: argparse.Namespace) -> int:
    from cosim.environment.factory import parallel_env
    from cosim.environment.policies import POLICIES

    _positive(args, "episodes")
    if args.seed is not None:  # with the seeds after it, before anything runs or is written
        check_seed("--seed", args.seed, args.episodes)
    env = parallel_env(args.config, config_overrides(args))  # a bad config fails here, before the folder is made
    if args.save_routes is not None:  # before SUMO starts: a bad folder is the user's error, not a lost run
        try:
            args.save_routes.mkdir(parents=True, exist_ok=True)
        except BaseException:
            env.close()
            raise
    try:
        first_seed = check_seed("sim.seed", env.cfg.sim.seed, args.episodes) if args.seed is None else args.seed
        for name in args.policy or ["scripted", "random"]:
            policy = POLICIES[name](first_seed)
            for ep in tqdm(range(args.episodes), desc=name, unit="ep", leave=False, disable=None):
                env.reset(seed=first_seed + ep)
                if args.save_routes is not None:
                    atomic_copy(env.route_file, args.save_routes / f"episode_{env.episode_seed}.rou.xml")
                while env.agents:
                    env.step(policy(env))
                s = env.last_summary
                if env.cfg.demand.enabled:  # a run of minutes under demand: its window's flow
                    log.info("%-8s seed %-4d throughput %4.0f veh/h (ramp %4.0f)  delay %5.1f s  ramp queue %4.1f veh  "
                             "LOS %s  (%d AVs)", name, s["seed"], s["throughput_total_vph"], s["throughput_ramp_vph"],
                             s["delay_mean_s"], s["ramp_queue_mean_veh"], s["los"], s["avs_released"])
                    continue
                log.info("%-8s seed %-4d crash %-5s merge %-5s mean distance %6.1f m  merger %6.1f m  (%d steps)",
                         name, s["seed"], s["crashed"], s["merged"], s["mean_distance"], s["merger_distance"],
                         s["length"])
    finally:
        env.close()
    return 0


# -- bench ---------------------------------------------------------------------------------------------
def _bench_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser)
    parser.add_argument("--episodes", type=int, default=20, help="episodes per measurement")
    parser.add_argument("--resets", type=int, default=40, help="resets per measurement")


def _bench(args: argparse.Namespace) -> int:
    from cosim.bench import bench
    from cosim.config import load_config

    _positive(args, "episodes", "resets")
    bench(load_config(args.config, config_overrides(args)), args.episodes, args.resets)
    return 0


# -- train ---------------------------------------------------------------------------------------------
def _train_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser)
    parser.add_argument("--out", type=Path, default=None, help="run folder (default: runs/<config stem>)")
    parser.add_argument("--workers", type=int, default=None, help="rollout worker processes (default: train.workers)")
    parser.add_argument("--episodes", type=int, default=None, help="episodes in total (default: train.episodes)")
    parser.add_argument("--budget-min", type=float, default=None,
                        help="wall-clock training budget over the whole run [min] (default: train.budget_min)")
    parser.add_argument("--resume", action="store_true", help="continue the run in --out from its checkpoint")
    parser.add_argument("--allow-config-change", action="store_true",
                        help="with --resume: continue although the config differs from the run's (the differences "
                             "are recorded in RUN/config_changes.yaml)")
    parser.add_argument("--init-from", type=Path, default=None, metavar="POLICY",
                        help="start a new run from these weights (a run folder, its policy.pt or best.pt, a shipped "
                             "policy) with a fresh optimizer: fine-tuning, or going on from a committed float16 "
                             "snapshot; not a resume (the run's counters start at 0); overrides train.init_from")
    parser.add_argument("--device", default=None, help="cpu | cuda | cuda:N (default: train.device)")
    _backend_arguments(parser)


def _train(args: argparse.Namespace) -> int:
    from agents.train import train
    from cosim.config import load_config

    _positive(args, "workers", "episodes")
    if args.budget_min is not None and args.budget_min < 0:
        raise ConfigError(f"--budget-min: must be >= 0, got {args.budget_min}")
    overrides = config_overrides(args)
    cfg = load_config(args.config, overrides=overrides)
    out = args.out or Path("runs") / Path(args.config).stem
    result = train(cfg, out, workers=args.workers, episodes=args.episodes, budget_min=args.budget_min,
                   resume=args.resume, device=args.device, allow_config_change=args.allow_config_change,
                   backend=args.backend, ray_address=args.ray_address, overrides=overrides,
                   init_from=args.init_from)
    log.info("trained %d episodes (%d updates, %d agent-samples, %.0f s) into %s", result.episodes, result.updates,
             result.samples, result.train_s, result.out_dir)
    return 130 if result.interrupted else 0


# -- sweep ---------------------------------------------------------------------------------------------
def _sweep_arguments(parser: argparse.ArgumentParser) -> None:
    from agents.sweep import BASELINES

    add_config_arguments(parser)
    parser.add_argument("--phi", type=float, nargs="+", required=True, metavar="RAD",
                        help="SVO angles [rad] to train, e.g. 0 0.3927 0.7854 1.1781 1.5708")
    parser.add_argument("--seeds", type=int, nargs="+", required=True, help="training seeds, e.g. 0 1 2")
    parser.add_argument("--budget-min", type=float, required=True, help="training wall-clock budget per run [min]")
    parser.add_argument("--eval-episodes", type=int, default=100, help="evaluation episodes per run and baseline")
    parser.add_argument("--eval-workers", type=int, default=2, help="evaluation worker processes")
    parser.add_argument("--baselines", nargs="*", choices=BASELINES, default=list(BASELINES))
    parser.add_argument("--demand", default=None, metavar="CONFIG",
                        help="also evaluate every run and baseline under this demand config's traffic (e.g. "
                             "configs/demand.yaml, --set applies to it too); the report gets a flow table")
    parser.add_argument("--out", type=Path, default=Path("runs/sweep"), help="sweep folder (default: %(default)s); "
                        "with --backend ray on several machines, on a file system they all share")
    _backend_arguments(parser)


def _sweep(args: argparse.Namespace) -> int:
    from agents.rollout import Backend
    from agents.sweep import sweep
    from cosim.config import load_config
    from cosim.evaluation.stats import format_table

    cfg = load_config(args.config, config_overrides(args))
    command = "cosim sweep " + " ".join(shlex.quote(a) for a in sys.argv[2:]) if sys.argv[1:2] == ["sweep"] else ""
    demand = load_config(args.demand, config_overrides(args)) if args.demand else None
    result = sweep(cfg, args.out, args.phi, args.seeds, args.budget_min, args.eval_episodes, args.eval_workers,
                   args.baselines, command, Backend(args.backend, args.ray_address), demand)
    log.info("wrote %s", args.out / "report.md")
    print(format_table(result["table"], result["episodes"]))
    return 0


# -- evaluate ------------------------------------------------------------------------------------------
def _policy_arguments(parser: argparse.ArgumentParser, policy_help: str) -> None:
    """What a command that plays a policy takes: the config options, and a run, a checkpoint or a baseline."""
    from cosim.evaluation.runner import BASELINES

    add_config_arguments(parser, default=None)
    parser.add_argument("--run", type=Path, help="training run folder (its config.yaml and checkpoint.pt)")
    parser.add_argument("--checkpoint", type=Path, help="checkpoint or policy file (default: RUN/best.pt, the best "
                        "policy by validation during training, where the run kept one, else RUN/policy.pt)")
    parser.add_argument("--last", action="store_true", help="the run's last policy (RUN/policy.pt), not its best")
    parser.add_argument("--policy", choices=["checkpoint", "sb3", *BASELINES], default="checkpoint", help=policy_help)


def _evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    _policy_arguments(parser, "a baseline instead of a checkpoint: sumo (SUMO drives the AVs), idle, random, "
                              "scripted (egoistic), courteous (lets the merging vehicle in); or sb3, a "
                              "Stable-Baselines3 model given by --checkpoint (scripts/train_sb3.py) "
                              "(default: checkpoint)")
    parser.add_argument("--episodes", type=int, help="evaluation episodes (default: evaluate.episodes, 100)")
    parser.add_argument("--seed", type=int, help=f"first evaluation seed (default: {EVAL_SEED_START:,}, disjoint "
                                                 "from training seeds)")
    parser.add_argument("--workers", type=int, help="worker processes (default: 1)")
    parser.add_argument("--sample", action="store_true", help="sample actions instead of the greedy argmax")
    parser.add_argument("--trajectories", type=int, help="episodes whose trajectories are plotted (default: 3)")
    parser.add_argument("--out", type=Path, help="output folder (default: RUN/eval)")
    parser.add_argument("--no-plots", action="store_true", help="skip the figures")
    parser.add_argument("--videos", type=int, default=0, metavar="K",
                        help="videos of the first K episodes in OUT/plots, linked from OUT/report.md (default: 0)")


def _evaluate(args: argparse.Namespace) -> int:
    from cosim.config import load_config
    from cosim.evaluation.runner import Baseline, check_counts, evaluate, evaluation_label
    from cosim.evaluation.stats import format_table

    if args.run is not None and not (args.run / "config.yaml").is_file():
        raise CosimError(f"--run {args.run}: not a training run folder (no config.yaml; `cosim train` writes one)")
    config = args.config or (args.run / "config.yaml" if args.run else DEFAULT_CONFIG)
    overrides = config_overrides(args)
    cfg = load_config(config, overrides)
    ec = cfg.evaluate
    # In demand mode an "episode" is a run of minutes: demand.seeds of them by default.
    episodes = args.episodes if args.episodes is not None else cfg.demand.seeds if cfg.demand.enabled else ec.episodes
    workers = ec.workers if args.workers is None else args.workers
    trajectories = ec.trajectories if args.trajectories is None else args.trajectories
    check_counts(episodes, workers, trajectories, prefix="--", videos=args.videos)
    seed = check_seed("--seed" if args.seed is not None else "evaluate.seed",
                      ec.seed if args.seed is None else args.seed, episodes)
    greedy = ec.greedy and not args.sample
    out = args.out or (args.run / "eval" if args.run else None)
    if out is None:
        raise CosimError("cosim evaluate: give --out DIR for a baseline without --run")
    policy = _trained_policy(args, greedy) if args.policy in ("checkpoint", "sb3") else Baseline(args.policy)
    summary = evaluate(cfg, policy, out, episodes=episodes, seed=seed,
                       workers=workers, trajectories=trajectories, confidence=ec.confidence, run_dir=args.run,
                       plots=not args.no_plots, videos=args.videos, overrides=overrides)
    log.info("wrote %s", Path(out) / "summary.json")
    label = evaluation_label(policy, args.run)  # as its report.md calls it
    print(format_table({label: summary["metrics"]}, {label: summary["episodes"]}, confidence=ec.confidence))
    return 0


def _trained_policy(args: argparse.Namespace, greedy: bool) -> Any:
    if args.policy == "sb3":
        if args.checkpoint is None or not args.checkpoint.is_file():
            raise CosimError(f"--policy sb3: give the model file with --checkpoint FILE (got {args.checkpoint})")
        try:
            from agents.sb3 import Sb3Policy
        except ImportError as exc:
            raise ConfigError(f"--policy sb3: {exc.name} is missing; pip install -e \".[sb3]\" installs it") from None
        return Sb3Policy(str(args.checkpoint.resolve()), greedy)
    from agents.checkpoint import TrainedPolicy, describe_checkpoint, find_checkpoint

    path = find_checkpoint(args.run, args.checkpoint, last=args.last)
    log.info("policy: %s", describe_checkpoint(path))
    return TrainedPolicy(str(path), greedy)


# -- check-net -----------------------------------------------------------------------------------------
def _check_net_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("net", type=Path, metavar="NET", help="the SUMO .net.xml (its description YAML beside it, "
                        "else inferred)")
    add_config_arguments(parser, net=False)
    parser.add_argument("--episodes", type=int, default=100, help="episodes per baseline (default: %(default)s)")
    parser.add_argument("--max-episodes", type=int, default=400,
                        help="more episodes, up to this many, while a target's interval straddles its bound "
                             "(default: %(default)s)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=EVAL_SEED_START, help="first evaluation seed")
    parser.add_argument("--suggest", action="store_true",
                        help="where the merge is no dilemma, measure settings that may make it one, one after the "
                             "other (--episodes each), and report the first that does")
    parser.add_argument("--out", type=Path, default=None,
                        help="keep the report (check.md, check.json) and the baselines' evaluations here "
                             "(default: a temporary folder, removed)")


def _check_net(args: argparse.Namespace) -> int:
    import tempfile

    from cosim.config import load_config
    from cosim.evaluation.checknet import check_net
    from cosim.scratch import run_folder

    _positive(args, "episodes", "workers")
    check_at_least("--max-episodes", args.max_episodes, args.episodes)
    check_seed("--seed", args.seed, args.max_episodes)
    args.overrides.append(f"net.file={args.net.resolve()}")
    if not args.net.is_file():
        raise ConfigError(f"NET {args.net}: not found (expected a SUMO .net.xml)")
    cfg = load_config(args.config, args.overrides)
    if args.out is not None:
        check_net(cfg, args.out, args.episodes, args.max_episodes, args.workers, args.seed, args.suggest)
        return 0
    with tempfile.TemporaryDirectory(prefix="cosim_check_", dir=run_folder()) as tmp:
        check_net(cfg, Path(tmp), args.episodes, args.max_episodes, args.workers, args.seed, args.suggest)
    return 0


# -- replay --------------------------------------------------------------------------------------------
def _replay_arguments(parser: argparse.ArgumentParser) -> None:
    _policy_arguments(parser, "a baseline instead of a checkpoint, as in `cosim evaluate` (default: checkpoint)")
    parser.add_argument("--seed", type=int, help=f"the episode's seed (default: evaluate.seed, {EVAL_SEED_START:,}: "
                                                 "the evaluation's first episode)")
    parser.add_argument("--sample", action="store_true", help="sample actions instead of the greedy argmax")
    parser.add_argument("--out", type=Path, help="folder of the video (default: RUN/replay, or runs/replay/POLICY)")
    parser.add_argument("--no-video", action="store_true", help="no video file (with --gui: only watch)")
    parser.add_argument("--gui", action="store_true", help="watch it live in sumo-gui (needs a display; "
                                                           "headless: xvfb-run -a cosim replay ...)")
    parser.add_argument("--delay", type=float, default=100.0, metavar="MS",
                        help="with --gui: sumo-gui's pause after each simulation step [ms] (default: %(default)s, "
                             "about real time at the default 0.1 s step)")
    parser.add_argument("--screenshot", type=Path, metavar="PNG",
                        help="with --gui: save sumo-gui's view after the episode")


def _replay(args: argparse.Namespace) -> int:
    import os

    from cosim.config import load_config
    from cosim.evaluation.replay import replay
    from cosim.evaluation.runner import Baseline

    if args.run is not None and not (args.run / "config.yaml").is_file():
        raise CosimError(f"--run {args.run}: not a training run folder (no config.yaml; `cosim train` writes one)")
    if args.policy in ("checkpoint", "sb3") and args.run is None and args.checkpoint is None:
        raise ConfigError("cosim replay: give --run RUN (or --checkpoint FILE) for a trained policy, or --policy "
                          "with a baseline")
    if args.screenshot is not None and not args.gui:
        raise ConfigError("--screenshot: sumo-gui's view; it needs --gui")
    if args.no_video and not args.gui:
        raise ConfigError("--no-video without --gui: nothing to show; drop --no-video or add --gui")
    if args.gui and not os.environ.get("DISPLAY"):
        raise ConfigError("--gui: no display (DISPLAY is unset); sumo-gui needs one: on a machine without a screen "
                          "run xvfb-run -a cosim replay ... (Debian: apt-get install xvfb)")
    check_at_least("--delay", args.delay, 0)
    config = args.config or (args.run / "config.yaml" if args.run else DEFAULT_CONFIG)
    cfg = load_config(config, config_overrides(args))
    if cfg.demand.enabled:
        raise ConfigError(f"{config}: demand.enabled: cosim replay films one episode of the episode scenario, not a "
                          "demand run of minutes; replay with an episode config (e.g. --config configs/default.yaml), "
                          "and see a demand run in its evaluation's flow figures (cosim evaluate --config ...)")
    seed = check_seed("--seed" if args.seed is not None else "evaluate.seed",
                      cfg.evaluate.seed if args.seed is None else args.seed)
    greedy = cfg.evaluate.greedy and not args.sample
    policy = _trained_policy(args, greedy) if args.policy in ("checkpoint", "sb3") else Baseline(args.policy)
    out = args.out or (args.run / "replay" if args.run else Path("runs") / "replay" / policy.name)
    row, video = replay(cfg, policy, seed, out, video=not args.no_video,
                        gui_delay=args.delay if args.gui else None, screenshot=args.screenshot)
    log.info("%s seed %d: crash %s, merge %s, merging vehicle %.1f m, %d decisions", policy.name, seed,
             row["crashed"], row["merged"], row["merger_distance"], row["length"])
    for what, path in (("video", video), ("screenshot", args.screenshot)):
        if path is not None:
            log.info("wrote %s %s", what, path)
    return 0


# -- compare -------------------------------------------------------------------------------------------
def _compare_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("runs", nargs="+", type=Path, help="evaluation folders, or run folders with eval/")
    parser.add_argument("--out", type=Path, default=Path("report"), help="report folder (default: %(default)s)")
    parser.add_argument("--labels", nargs="+", help="one label per run (default: folder names)")


def _compare(args: argparse.Namespace) -> int:
    from cosim.evaluation.compare import compare
    from cosim.evaluation.stats import format_table

    result = compare(args.runs, args.out, args.labels)
    log.info("wrote %s", args.out / "report.md")
    print(format_table({k: v["metrics"] for k, v in result.items()},
                       {k: int(v["episodes"]) for k, v in result.items()}))
    return 0


Command = tuple[str, Callable[[argparse.ArgumentParser], None], Callable[[argparse.Namespace], int]]
COMMANDS: dict[str, Command] = {
    "build-net": ("build an on-ramp merge network with netconvert", _build_net_arguments, _build_net),
    "run-scenario": ("run the env with a scripted or random policy", _run_scenario_arguments, _run_scenario),
    "bench": ("measure env speed against a bare libsumo loop", _bench_arguments, _bench),
    "check-net": ("pre-flight of a net: its summary, the scenario on it, the baselines and a dilemma verdict",
                  _check_net_arguments, _check_net),
    "train": ("train AV policies with multi-agent A2C or PPO", _train_arguments, _train),
    "sweep": ("train and evaluate every (SVO angle, seed) within a budget, report against baselines",
              _sweep_arguments, _sweep),
    "evaluate": ("evaluate trained AVs or a baseline policy", _evaluate_arguments, _evaluate),
    "replay": ("watch one episode: live in sumo-gui and as a video", _replay_arguments, _replay),
    "compare": ("compare evaluated runs: tables, plots, Markdown report", _compare_arguments, _compare),
}


def main(argv: Sequence[str] | None = None) -> int:
    as_program = argv is None  # the process ends with this call (console script, python -m cosim.cli)
    argv = list(sys.argv[1:] if argv is None else argv)
    parser = argparse.ArgumentParser(prog="cosim", description=__doc__.splitlines()[0])
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name, (help_text, _, _) in COMMANDS.items():
        sub.add_parser(name, help=help_text, add_help=False)
    # Parse up to the command name first, so that only the chosen command's imports happen.
    at = next((i for i, a in enumerate(argv) if a in COMMANDS), len(argv))
    head = parser.parse_args(argv[: at + 1])
    help_text, add_arguments, run = COMMANDS[head.command]
    full = argparse.ArgumentParser(prog=f"cosim {head.command}", description=help_text)
    full.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    add_arguments(full)
    args = full.parse_args(argv[at + 1:])
    logging.basicConfig(level=logging.DEBUG if args.verbose or head.verbose else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    previous = signal.signal(signal.SIGTERM, _terminate)  # a scheduler's stop is handled like Ctrl-C
    try:
        with logging_redirect_tqdm():  # log lines above progress bars, not through them
            return int(run(args) or 0)
    except CosimError as exc:
        log.error("%s", exc)
        return 2
    except OSError as exc:
        where = f" {exc.filename}:" if exc.filename else ""
        log.error("cosim %s:%s %s", head.command, where, exc.strerror or exc)
        return 2
    except KeyboardInterrupt:
        log.warning("cosim %s: interrupted", head.command)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)
        if as_program:
            # The command's work and exit status are settled: a late Ctrl-C (a second one just after a stop) must
            # not cut short the exit's clean-up (workers joined, temporary folders removed) or change the status.
            signal.signal(signal.SIGINT, signal.SIG_IGN)


def _terminate(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


if __name__ == "__main__":
    raise SystemExit(main())
