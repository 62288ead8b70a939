"""Training speed: agent-samples/s for W = 1, 2, 4 rollout workers, rollout vs update time share, and the
forward+backward time of the paper-size network on one batch.

    .venv/bin/python scripts/bench_train.py                 # fake env with the default preset's observations
    .venv/bin/python scripts/bench_train.py --env cosim --config configs/smoke.yaml

`--env fake` uses agents.fake_env.CueEnv shaped like the default preset (5x4x32x128, float32, 4 AVs);
`--env cosim` trains on the real env built from `--config` (`cosim.parallel_env`). Results are logged and,
with `--json`, written to a file.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path
from typing import Any

import torch

from agents.a2c import a2c_loss
from agents.fake_env import make_fake_env
from agents.model import ActorCritic
from agents.rollout import EnvFactory
from agents.train import train
from cosim.config import OBSERVATION_PRESETS, load_config

log = logging.getLogger("bench_train")


def fake_factory(n_avs: int, horizon: int) -> EnvFactory:
    p = OBSERVATION_PRESETS["default"]
    return make_fake_env(n_agents=n_avs, obs_shape=(p["frames"], 4, p["height_px"], p["width_px"]),
                         horizon=horizon)


def bench_workers(args: argparse.Namespace) -> list[dict[str, Any]]:
    cfg = load_config(args.config, overrides=args.overrides)
    rows = []
    for workers in args.workers:
        factory = fake_factory(cfg.scenario.n_avs, args.horizon) if args.env == "fake" else None
        with tempfile.TemporaryDirectory() as tmp:
            res = train(cfg, Path(tmp) / "run", workers=workers, episodes=args.episodes * workers,
                        device=args.device, env_factory=factory, progress=False)
        busy = res.rollout_s + res.update_s
        rows.append({"workers": workers, "episodes": res.episodes, "updates": res.updates,
                     "samples": res.new_samples, "wall_s": round(res.wall_s, 2),
                     "samples_per_s": round(res.new_samples / res.wall_s, 1),
                     "rollout_share": round(res.rollout_s / busy, 3), "update_share": round(res.update_s / busy, 3)})
        log.info("W=%d: %s", workers, rows[-1])
    return rows


def bench_paper_network(batch: int, device: str, reps: int = 3) -> dict[str, Any]:
    p = OBSERVATION_PRESETS["paper"]
    shape = (p["frames"], 4, p["height_px"], p["width_px"])
    torch.manual_seed(0)
    net = ActorCritic(shape).to(device)
    obs = torch.rand(batch, *shape, device=device)
    actions = torch.randint(0, 5, (batch,), device=device)
    adv, ret = torch.randn(batch, device=device), torch.randn(batch, device=device)
    times = []
    for _ in range(reps + 1):  # the first is a warm-up
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        logits, values = net(obs)
        a2c_loss(logits, values, actions, adv, ret, 0.01, 0.5).loss.backward()
        net.zero_grad(set_to_none=True)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    row = {"obs_shape": list(shape), "batch": batch, "params": sum(q.numel() for q in net.parameters()),
           "fwd_bwd_s": round(min(times[1:]), 4), "device": device}
    log.info("paper network: %s", row)
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", choices=("fake", "cosim"), default="fake")
    parser.add_argument("--config", default=None, help="experiment YAML (default: built-in defaults)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--episodes", type=int, default=6, help="episodes per worker per measurement")
    parser.add_argument("--horizon", type=int, default=20, help="fake env episode length [decisions]")
    parser.add_argument("--batch", type=int, default=20, help="paper network batch (default T*W = 5*4)")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--json", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    logging.getLogger("agents").setLevel(logging.WARNING)
    result = {"env": args.env, "threads": torch.get_num_threads(), "workers": bench_workers(args),
              "paper_network": bench_paper_network(args.batch, args.device)}
    if args.json:
        args.json.write_text(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
