"""Training speed against the machine's limit: agent-samples/s for each algorithm and worker count, the share of the
limit it reaches, the rollout/update split, and the network's forward+backward time at the default and paper presets.

    python scripts/bench_train.py --workers 12 --algo ppo a2c --json results/bench_train.json
    python scripts/bench_train.py --workers 1 2 4 8 --seconds 60 --algo ppo
    python scripts/bench_train.py --backend local ray --workers 2 --algo ppo --no-network   # Ray's overhead
    python scripts/bench_train.py --device cuda --paper        # on a GPU: the paper preset's training figure too

Each measurement trains a fresh run for `--seconds` of training wall time (`train.budget_min`) and reports
agent-samples collected per second of wall time, and how that time splits between collecting (env steps,
acting, moving observations) and learning. Beside it, timed in the same run, the machine's limit for it:

    limit = 1 / (network seconds per agent-sample + env seconds per agent-sample / cores)

the network's share being its textbook passes at training's batch sizes on all cores (one acting forward at the
size training acts in, half the workers' AVs at once, plus each update pass: PPO's epochs x minibatches of
forward+backward+step, A2C's one over the whole batch, at the run's own samples per update and in the precision
training chose), the env's a bare libsumo loop with the VelocityMap (`cosim.bench.measure`) per AV, spread over the
cores. `share` = samples_per_s / limit: work saved below the textbook passes shows as a share above what it was.
Results are logged and, with `--json`, written to a file (`samples_per_s`, `limit_samples_per_s`, `share`).
`--config configs/demand.yaml` measures training under demand (segments of continuing runs); its limit takes the
env's share from the episode scenario's bare loop on the same net, so its share is a rough one.
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
from agents.multiagent import MultiAgentPolicy
from agents.rollout import BACKENDS
from agents.train import TORCH_THREADS, train
from cosim.bench import measure
from cosim.config import OBSERVATION_PRESETS, Config, load_config
from cosim.files import atomic_write_text, read_csv

log = logging.getLogger("bench_train")
CORES = TORCH_THREADS  # torch's default: the cores it may use
LAST = {False: "crashed", True: "collisions"}  # episodes.csv's measure of how far a run learnt, without / with demand


def bench_workers(args: argparse.Namespace, algo: str, preset: str, env_s: float) -> list[dict[str, Any]]:
    """Train for --seconds at each backend and worker count; `env_s`: the bare loop's seconds per agent-sample."""
    # No validation: its greedy episodes are not training's samples.
    cfg = load_config(args.config, overrides=[*args.overrides, f"observation.preset={preset}", f"train.algo={algo}",
                                              f"train.precision={args.precision}", "train.eval_every=0"])
    rows = []
    for backend, workers in itertools.product(args.backend, args.workers):
        with tempfile.TemporaryDirectory() as tmp:
            res = train(cfg, Path(tmp) / "run", workers=workers, budget_min=args.seconds / 60.0, device=args.device,
                        progress=False, backend=backend)
            # How far it learnt in that time: the crash rate of its last 100 training episodes (sampled actions);
            # under demand the collisions per run.
            last = [float(r[LAST[cfg.demand.enabled]]) for r in read_csv(Path(tmp) / "run" / "episodes.csv")[-100:]]
        busy = res.rollout_s + res.update_s
        rate = res.new_samples / res.wall_s
        net = network_seconds(cfg, workers, res.new_samples / max(res.updates, 1), args.device)
        limit = 1.0 / (net["per_sample_s"] + env_s / CORES)
        rows.append({"algo": algo, "preset": preset, "backend": backend, "workers": workers, "episodes": res.episodes,
                     "updates": res.updates, "samples": res.new_samples, "wall_s": round(res.wall_s, 1),
                     "samples_per_s": round(rate, 1), "limit_samples_per_s": round(limit, 1),
                     "share": round(rate / limit, 3), "network": net, "env_s_per_sample": env_s,
                     "rollout_share": round(res.rollout_s / busy, 3), "update_share": round(res.update_s / busy, 3),
                     f"last_100_{LAST[cfg.demand.enabled]}": round(sum(last) / max(len(last), 1), 2)})
        log.info("%s, %s preset, %s W=%d: %.0f agent-samples/s, the limit %.0f: share %.2f (rollout %.0f%% / update "
                 "%.0f%%; network %.3f ms + env %.3f ms / %d cores per agent-sample, %s), %d episodes in %.0f s, %s of "
                 "the last 100 %.2f", algo, preset, backend, workers, rate, limit, rate / limit,
                 100 * rows[-1]["rollout_share"], 100 * rows[-1]["update_share"], 1e3 * net["per_sample_s"],
                 1e3 * env_s, CORES, net["precision"], res.episodes, res.wall_s, LAST[cfg.demand.enabled],
                 sum(last) / max(len(last), 1))
    return rows


def network_seconds(cfg: Config, workers: int, batch: float, device: str, reps: int = 10) -> dict[str, Any]:
    """The textbook passes of one agent-sample (module doc) for `cfg`'s network and algorithm, on all cores, at
    `batch` samples per update, in the precision training chooses for it (train.precision)."""
    tc = cfg.train
    n_agents, shape = cfg.scenario.n_avs, cfg.observation.shape
    torch.set_num_threads(CORES)
    torch.manual_seed(0)
    policy = MultiAgentPolicy(n_agents, shape, 5, tc, device)
    net, opt = policy.nets[0], policy.optimizers[0]
    acting = max(1, (workers + 1) // 2 * n_agents)  # collect acts for half the workers' AVs at once
    size = max(1, round(batch))
    # PPO: epochs x minibatches passes over minibatches; A2C: one pass over the whole batch.
    mb, count = (max(1, size // tc.ppo_minibatches), tc.ppo_epochs * tc.ppo_minibatches) if tc.algo == "ppo" else \
        (size, 1)

    def timed(fn: Any) -> float:
        times = []
        for _ in range(reps + 1):  # the first is a warm-up
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            t0 = time.perf_counter()
            fn()
            if device.startswith("cuda"):
                torch.cuda.synchronize()
            times.append(time.perf_counter() - t0)
        return min(times[1:])

    x_act = torch.randint(0, 256, (acting, *shape), dtype=torch.uint8, device=device)
    x = torch.randint(0, 256, (mb, *shape), dtype=torch.uint8, device=device)
    a = torch.randint(0, 5, (mb,), device=device)
    adv, ret, logp = (torch.randn(mb, device=device) for _ in range(3))

    def update_pass() -> None:
        logits, values = net(x)
        loss = actor_critic_loss(logits, values, a, adv, ret, tc.entropy_coef, tc.value_coef, logp,
                                 tc.clip_range if tc.algo == "ppo" else None).loss
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()

    with torch.no_grad():
        act_s = timed(lambda: net(x_act)) / acting
    update_s = timed(update_pass) * count / size
    return {"per_sample_s": act_s + update_s, "act_s": act_s, "update_s": update_s, "acting_batch": acting,
            "update_batch": size, "minibatch": mb, "passes": count,
            "precision": "bfloat16" if policy.bf16 else "float32"}


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
    cfg = load_config(args.config, args.overrides)
    flags = sorted({f for f in ("avx512_bf16", "amx_bf16") if f in Path("/proc/cpuinfo").read_text()}) \
        if Path("/proc/cpuinfo").is_file() else []
    log.info("torch %s, %d cores, device %s, CPU flags %s, bf16 %s", torch.__version__, CORES, args.device,
             flags or "none of avx512_bf16/amx_bf16", use_bf16(args.precision, args.device))
    # Under demand the episode scenario's bare loop on the same net stands in for the env's share of the limit.
    bare = measure(load_config(cfg, {"demand.enabled": False}), episodes=20, resets=1)["bare"]
    env_s = bare["velocity_map"] / cfg.scenario.n_avs
    log.info("bare libsumo loop with the VelocityMap: %.3f ms per decision of %d AVs", 1e3 * bare["velocity_map"],
             cfg.scenario.n_avs)
    result: dict[str, Any] = {"cores": CORES, "cpu_flags": flags, "device": args.device, "torch": torch.__version__,
                              "bare_loop_s_per_decision": bare["velocity_map"], "workers": []}
    for algo in args.algo:
        for preset in ("default", "paper") if args.paper else ("default",):
            result["workers"] += bench_workers(args, algo, preset, env_s)
    if not args.no_network:
        result["network"] = [bench_network(preset, 64, args.device, bf16)
                             for preset in ("default", "paper") for bf16 in (False, True)]
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
