"""How fast a demand run goes: a 12-minute window (2 min warm-up, 10 min measured) with about 20 AVs present at
once, every AV driven by the default network each decision, against the time it simulates; and what it writes.

    python scripts/bench_demand.py --run runs/alt              # a trained run's network
    python scripts/bench_demand.py                             # the default network, untrained (the same work)

Runs `cosim evaluate` in demand mode (configs/demand.yaml, `--set demand.av_penetration=0.8`: about 20 AVs in
the net at once on the default net) for `--seeds` runs in one process, and prints per run the wall time, the
simulated time, their ratio (the target: at most 1/10), the most AVs present at once and the size of its outputs
(SUMO's files and the record). `--json` writes the same.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import torch

from agents.checkpoint import TrainedPolicy, find_checkpoint, save_checkpoint
from agents.model import ActorCritic
from cosim.config import load_config
from cosim.errors import run_script
from cosim.evaluation.runner import evaluate
from cosim.files import read_csv

log = logging.getLogger("bench_demand")


def untrained_checkpoint(cfg, folder: Path) -> Path:  # noqa: ANN001 - a Config
    """The default network with its initial weights, saved as a run's checkpoint: the same work as a trained one."""
    o = cfg.observation
    shape = o.shape
    net = ActorCritic(shape, 5, feature_dim=cfg.train.feature_dim, head_hidden=cfg.train.head_hidden)
    spec = {"agents": ["av_0"], "obs_shape": list(shape), "obs_dtype": o.dtype, "n_actions": 5, "shared_policy": True,
            "feature_dim": cfg.train.feature_dim, "head_hidden": cfg.train.head_hidden}
    path = folder / "checkpoint.pt"
    save_checkpoint(path, {"spec": spec, "policy": {"nets": [net.state_dict()]}, "counters": {"updates": 0},
                           "rng": {}})
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--run", type=Path, default=None, help="a training run whose network drives the AVs")
    parser.add_argument("--config", default="configs/demand.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=["demand.av_penetration=0.8"],
                        metavar="KEY=VALUE")
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    torch.set_num_threads(2)
    cfg = load_config(args.config, args.overrides)
    results = []
    with tempfile.TemporaryDirectory(prefix="bench_demand_") as tmp:
        ckpt = find_checkpoint(args.run, None) if args.run else untrained_checkpoint(cfg, Path(tmp))
        policy = TrainedPolicy(str(ckpt))
        for k in range(args.seeds):
            out = Path(tmp) / f"eval_{k}"
            t0 = time.perf_counter()
            evaluate(cfg, policy, out, episodes=1, seed=10_000_000 + k, workers=1, plots=False)
            wall = time.perf_counter() - t0
            (row,) = read_csv(out / "episodes.csv")
            size = sum(p.stat().st_size for p in (out / "sumo").rglob("*") if p.is_file())
            sim = cfg.demand.warmup + cfg.demand.window
            results.append({"seed": 10_000_000 + k, "wall_s": wall, "simulated_s": sim, "ratio": wall / sim,
                            "avs_present_max": int(row["avs_present_max"]), "avs_released": int(row["avs_released"]),
                            "outputs_mb": size / 2**20})
            log.info("seed %d: %.1f s for %.0f s simulated (1/%.1f), at most %s AVs present (%s released), "
                     "outputs %.1f MB", 10_000_000 + k, wall, sim, sim / wall, row["avs_present_max"],
                     row["avs_released"], size / 2**20)
    print(json.dumps({"network": str(args.run or "untrained default"), "threads": torch.get_num_threads(),
                      "runs": results}, indent=2))
    if args.json:
        args.json.write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    run_script(main, log)
