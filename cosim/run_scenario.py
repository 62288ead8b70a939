"""`cosim run-scenario`: run the env with a hand-written policy and print each episode's outcome."""

from __future__ import annotations

import argparse
import logging
import shutil
from pathlib import Path

from tqdm import tqdm

from cosim.cli import add_config_arguments
from cosim.environment.merge_env import parallel_env
from cosim.environment.policies import POLICIES

log = logging.getLogger(__name__)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_config_arguments(parser)
    parser.add_argument("--episodes", type=int, default=3, help="episodes to run (default: %(default)s)")
    parser.add_argument("--policy", choices=sorted(POLICIES), action="append",
                        help="policy to run, repeatable (default: scripted and random)")
    parser.add_argument("--seed", type=int, default=None, help="first episode's seed (default: config)")
    parser.add_argument("--save-routes", type=Path, default=None, metavar="DIR",
                        help="keep each episode's SUMO route file (vTypes, routes, vehicles) here, e.g. to "
                             "open it with sumo-gui -n NET -r DIR/episode_SEED.rou.xml")


def run(args: argparse.Namespace) -> int:
    if args.save_routes is not None:  # before SUMO starts: a bad folder is the user's error, not a lost run
        args.save_routes.mkdir(parents=True, exist_ok=True)
    env = parallel_env(args.config, args.overrides)
    try:
        first_seed = env.cfg.sim.seed if args.seed is None else args.seed
        for name in args.policy or ["scripted", "random"]:
            policy = POLICIES[name](first_seed)
            for ep in tqdm(range(args.episodes), desc=name, unit="ep", leave=False, disable=None):
                env.reset(seed=first_seed + ep)
                if args.save_routes is not None:
                    shutil.copy(env.route_file, args.save_routes / f"episode_{env.episode_seed}.rou.xml")
                infos: dict = {}
                while env.agents:
                    _, _, _, _, infos = env.step(policy(env))
                s = next(iter(infos.values()))["episode"]
                log.info("%-8s seed %-4d crash %-5s merge %-5s mean distance %6.1f m  merger %6.1f m  (%d steps)",
                         name, s["seed"], s["crashed"], s["merged"], s["mean_distance"], s["merger_distance"],
                         s["length"])
    finally:
        env.close()
    return 0
