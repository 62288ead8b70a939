"""Another learning library on the env: a parameter-shared PPO from Stable-Baselines3, trained through SuperSuit.

    pip install -e ".[sb3]"
    python scripts/train_sb3.py --config configs/default.yaml --steps 200000 --envs 4 --out runs/sb3
    # trains into runs/sb3/model.zip, then evaluates it as this does (again, or on other seeds / nets):
    cosim evaluate --config configs/default.yaml --policy sb3 --checkpoint runs/sb3/model.zip --out runs/sb3/eval

How another library plugs in (`agents/sb3.py`): the env is a PettingZoo ParallelEnv (`cosim.parallel_env`);
SuperSuit's wrappers make every AV of `--envs` env copies (one process, one SUMO each) a sub-env of one
vector env, so one network is shared by all AVs; the policy's features extractor is the paper's Conv3D stack,
and the config's `train:` section sets PPO as for `cosim train` (`--set train.lr=...` applies).
The saved `model.zip` is then evaluated as `cosim evaluate --policy sb3` evaluates it: on the evaluation
seeds, with the same metrics and files as the project's own policies (`--eval-episodes 0` skips it).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

from cosim.config import Config, load_config
from cosim.errors import CosimError

log = logging.getLogger("train_sb3")

MODEL_NAME = "model.zip"


def train_sb3(config: Config, out: Path, steps: int, envs: int, seed: int) -> Path:
    """Train SB3's PPO for `steps` agent-steps into `out/model.zip`; returns its path."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.utils import set_random_seed

    from agents.config import train_config
    from agents.sb3 import make_vec_env, ppo_kwargs, sb3_train_config

    tc = sb3_train_config(train_config(config))  # lr, gamma, epochs, network sizes... as `cosim train` uses them
    vec = make_vec_env(config, envs, seed)
    set_random_seed(seed)  # not PPO(seed=...): SuperSuit's process vector env has no seed() to pass it on to
    try:
        n_steps = 128  # per sub-env (AV) and rollout
        model = PPO("MlpPolicy", vec, device=tc.device, **ppo_kwargs(tc, n_steps, n_steps * vec.num_envs))
        model.learn(total_timesteps=steps)
    finally:
        vec.close()
    out.mkdir(parents=True, exist_ok=True)
    path = out / MODEL_NAME
    model.save(path)
    return path


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--steps", type=int, default=200_000, help="agent-steps to train (all AVs of all envs)")
    parser.add_argument("--envs", type=int, default=2, help="env copies, one process (one SUMO) each")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--eval-episodes", type=int, default=100, help="evaluation episodes after training")
    parser.add_argument("--eval-workers", type=int, default=2, help="evaluation worker processes")
    parser.add_argument("--out", type=Path, default=Path("runs/sb3"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s",
                        datefmt="%H:%M:%S")
    try:
        import agents.sb3  # noqa: F401 - the extra's packages, checked before any work
    except ImportError as exc:
        print(f"error: {exc.name} is missing; install the extra: pip install -e \".[sb3]\"", file=sys.stderr)
        return 2
    try:
        if args.steps <= 0 or args.envs <= 0 or args.seed < 0 or args.eval_episodes < 0 or args.eval_workers <= 0:
            raise CosimError("--steps, --envs and --eval-workers: must be > 0; --seed and --eval-episodes: >= 0")
        if (args.out / MODEL_NAME).exists():
            raise CosimError(f"--out {args.out}: holds a {MODEL_NAME} already; choose another folder")
        config = load_config(args.config, args.overrides)
        t0 = time.perf_counter()
        path = train_sb3(config, args.out, args.steps, args.envs, args.seed)
        log.info("trained %d agent-steps in %.0f s into %s", args.steps, time.perf_counter() - t0, path)
        if args.eval_episodes:
            from agents.sb3 import Sb3Policy
            from cosim.evaluation.runner import evaluate
            from cosim.evaluation.stats import format_table

            summary = evaluate(config, Sb3Policy(str(path.resolve())), args.out / "eval",
                               episodes=args.eval_episodes, workers=args.eval_workers, plots=False)
            print(format_table({"sb3": summary["metrics"]}, {"sb3": summary["episodes"]}))
    except CosimError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
