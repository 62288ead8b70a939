"""Training speed: agent-samples/s for 1, 2 and 4 rollout workers (and more), the rollout/update time split, and the
forward+backward time of the network at the default and paper presets, float32 vs bfloat16.

    python scripts/bench_train.py                              # configs/default.yaml on real SUMO, A2C and PPO
    python scripts/bench_train.py --workers 1 2 4 8 --seconds 60 --algo ppo
    python scripts/bench_train.py --backend local ray --workers 2 --algo ppo --no-network   # Ray's overhead
    python scripts/bench_train.py --device cuda --paper        # on a GPU: the paper preset's training figure too

Each measurement trains a fresh run for `--seconds` of training wall time (`train.budget_min`) and reports
agent-samples collected per second of wall time, and how that time splits between collecting (env steps,
acting, moving observations) and learning. Results are logged and, with `--json`, written to a file.
"""

from __future__ import annotations

import argparse
import itertools
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from agents.config import use_bf16
from agents.losses import actor_critic_loss
from agents.model import ActorCritic
from agents.rollout import BACKENDS
from agents.train import train
from cosim.config import OBSERVATION_PRESETS, load_config
from cosim.files import read_csv

log = logging.getLogger("bench_train")


def bench_workers(args: argparse.Namespace, algo: str, preset: str) -> list[dict[str, Any]]:
    cfg = load_config(args.config, overrides=[*args.overrides, f"observation.preset={preset}", f"train.algo={algo}",
                                              f"train.precision={args.precision}"])
    rows = []
    for backend, workers in itertools.product(args.backend, args.workers):
        with tempfile.TemporaryDirectory() as tmp:
            res = train(cfg, Path(tmp) / "run", workers=workers, budget_min=args.seconds / 60.0, device=args.device,
                        progress=False, backend=backend)
            # How far it learnt in that time: the crash rate of its last 100 training episodes (sampled actions).
            last = [float(r["crashed"]) for r in read_csv(Path(tmp) / "run" / "episodes.csv")[-100:]]
        busy = res.rollout_s + res.update_s
        rows.append({"algo": algo, "preset": preset, "backend": backend, "workers": workers, "episodes": res.episodes,
                     "updates": res.updates, "samples": res.new_samples, "wall_s": round(res.wall_s, 1),
                     "samples_per_s": round(res.new_samples / res.wall_s, 1),
                     "rollout_share": round(res.rollout_s / busy, 3), "update_share": round(res.update_s / busy, 3),
                     "last_100_crash": round(sum(last) / max(len(last), 1), 2)})
        log.info("%s, %s preset, %s W=%d: %.0f agent-samples/s (rollout %.0f%% / update %.0f%%), %d episodes in "
                 "%.0f s, crash rate of the last 100 %.2f", algo, preset, backend, workers, rows[-1]["samples_per_s"],
                 100 * rows[-1]["rollout_share"], 100 * rows[-1]["update_share"], res.episodes, res.wall_s,
                 rows[-1]["last_100_crash"])
    return rows


def bench_network(preset: str, batch: int, device: str, bf16: bool, reps: int = 3) -> dict[str, Any]:
    p = OBSERVATION_PRESETS[preset]
    shape = (p["frames"], 4, p["height_px"], p["width_px"])
    torch.manual_seed(0)
    net = ActorCritic(shape, bf16=bf16).to(device)
    obs = torch.randint(0, 256, (batch, *shape), dtype=torch.uint8, device=device)
    actions = torch.randint(0, 5, (batch,), device=device)
    adv, ret = torch.randn(batch, device=device), torch.randn(batch, device=device)
    times = []
    for _ in range(reps + 1):  # the first is a warm-up
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        logits, values = net(obs)
        actor_critic_loss(logits, values, actions, adv, ret, 0.01, 0.5).loss.backward()
        net.zero_grad(set_to_none=True)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    best = min(times[1:])
    row = {"preset": preset, "obs_shape": list(shape), "batch": batch, "bf16": bf16, "device": device,
           "fwd_bwd_ms_per_sample": round(1e3 * best / batch, 3)}
    log.info("network %s: %s", preset, row)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", default="configs/default.yaml")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--algo", nargs="+", choices=("a2c", "ppo"), default=["a2c", "ppo"])
    parser.add_argument("--seconds", type=float, default=45.0, help="training wall time per measurement")
    parser.add_argument("--precision", choices=("auto", "float32", "bfloat16"), default="auto")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--backend", nargs="+", choices=BACKENDS, default=["local"],
                        help="rollout workers as local processes and/or Ray actors (the overhead of Ray)")
    parser.add_argument("--paper", action="store_true", help="also train with the paper preset (10x4x64x512)")
    parser.add_argument("--no-network", action="store_true", help="skip the network's forward+backward timing")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("agents").setLevel(logging.WARNING)
    log.info("torch %s, %d threads, device %s, bf16 %s", torch.__version__, torch.get_num_threads(), args.device,
             use_bf16(args.precision, args.device))
    result: dict[str, Any] = {"threads": torch.get_num_threads(), "device": args.device, "workers": []}
    for algo in args.algo:
        for preset in ("default", "paper") if args.paper else ("default",):
            result["workers"] += bench_workers(args, algo, preset)
    if not args.no_network:
        result["network"] = [bench_network(preset, 64, args.device, bf16)
                             for preset in ("default", "paper") for bf16 in (False, True)]
    if args.json:
        args.json.write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
