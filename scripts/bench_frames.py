"""Time the network with each frame through its first two layers once, against the whole observations, in one process.

An agent's VelocityMap stack shifts by one frame per decision, the first Conv3D's depth kernel is 1 and the second's
depth stride 1, so a frame's part in the first two layers is the same wherever it stands in a stack, and of a
sample's F frames F - 1 were in the sample before it. Two measurements, the two sides interleaved call by call so
that a machine whose speed drifts slows both alike (medians over `--reps`):

- acting: one forward of `--acting` observations that continue their slots' last ones through
  `agents.model.FrameMemory` (the first two layers on the newest frames only), against `ActorCritic.forward` of the
  same observations (Table 1's Conv3D stack), on one thread (training acts on one while the workers step on the other
  core);
- update: one forward+backward of `--update` samples drawn from agents' runs of `--run` consecutive decisions,
  given as their distinct frames (`ActorCritic.forward_frames`: 1 + (F - 1) / run frames per sample), against the
  whole observations, on all cores, with the loss of A2C.

    python scripts/bench_frames.py [--preset default] [--acting 24] [--update 128] [--run 20] [--reps 20]

Random pixels, the input standardised (`train.obs_norm`), float32 unless `--bf16`.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

# Run from a checkout without installing: the repository root holds the `agents` and `cosim` packages.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from agents.losses import actor_critic_loss  # noqa: E402
from agents.model import ActorCritic, FrameMemory  # noqa: E402
from agents.train import TORCH_THREADS  # noqa: E402
from cosim.config import OBSERVATION_PRESETS  # noqa: E402


def interleaved(a: Callable[[], object], b: Callable[[], object], reps: int) -> tuple[float, float]:
    """Median seconds of `a` and of `b`, called alternately `reps` times each after one warm-up call."""
    a(), b()
    times: tuple[list[float], list[float]] = ([], [])
    for _ in range(reps):
        for fn, out in ((a, times[0]), (b, times[1])):
            t0 = time.perf_counter()
            fn()
            out.append(time.perf_counter() - t0)
    return statistics.median(times[0]), statistics.median(times[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--preset", choices=sorted(OBSERVATION_PRESETS), default="default")
    parser.add_argument("--acting", type=int, default=24, help="observations per acting forward (half of 12 workers' "
                                                                   "4 AVs)")
    parser.add_argument("--update", type=int, default=128, help="samples per update pass (agents.multiagent."
                                                                    "UPDATE_CHUNK)")
    parser.add_argument("--run", type=int, default=20, help="consecutive decisions of an agent in the update's samples")
    parser.add_argument("--reps", type=int, default=20)
    parser.add_argument("--bf16", action="store_true", help="bfloat16 autocast, as training on CPUs with it")
    args = parser.parse_args()
    p = OBSERVATION_PRESETS[args.preset]
    shape = (p["frames"], 4, p["height_px"], p["width_px"])
    f = shape[0]
    torch.manual_seed(0)
    net = ActorCritic(shape, obs_norm=True, bf16=args.bf16)
    net.obs_norm.update(torch.randint(0, 256, (256, *shape[1:]), dtype=torch.uint8))

    def observations(n: int) -> torch.Tensor:  # stored channels last, as the learner's batch stores them
        return torch.randint(0, 256, (n, f, *shape[2:], shape[1]), dtype=torch.uint8).permute(0, 1, 4, 2, 3)

    torch.set_num_threads(1)
    obs = observations(args.acting)
    slots = torch.arange(args.acting)
    memory = FrameMemory(net)
    with torch.no_grad():
        memory(obs, slots, torch.zeros(args.acting, dtype=torch.bool))  # every slot's first stack
        continuing = torch.ones(args.acting, dtype=torch.bool)
        whole, shared = interleaved(lambda: net(obs), lambda: memory(obs, slots, continuing), args.reps)
    print(f"acting, {args.acting} observations {shape}, 1 thread: whole {1e3 * whole:.2f} ms, through FrameMemory "
          f"{1e3 * shared:.2f} ms: {shared / whole:.2f}")

    torch.set_num_threads(TORCH_THREADS)
    n = args.update
    runs = -(-n // args.run)
    # Run r's frames are r * (run + F - 1) + 0 .. run + F - 2; its sample k holds frames k .. k + F - 1.
    index = torch.stack([r * (args.run + f - 1) + k + torch.arange(f) for r in range(runs)
                         for k in range(args.run)])[:n]
    frames = torch.randint(0, 256, (runs * (args.run + f - 1), *shape[2:], shape[1]),
                           dtype=torch.uint8).permute(0, 3, 1, 2)
    used, index = index.unique(return_inverse=True)
    frames = frames[used]
    stacked = frames[index]  # (n, F, C, H, W): the same observations, whole
    actions, adv, ret = torch.randint(0, 5, (n,)), torch.randn(n), torch.randn(n)

    def step(forward: Callable[[], tuple[torch.Tensor, torch.Tensor]]) -> None:
        logits, values = forward()
        actor_critic_loss(logits, values, actions, adv, ret, 0.01, 0.5).loss.backward()
        net.zero_grad(set_to_none=True)

    whole, shared = interleaved(lambda: step(lambda: net(stacked)),
                                lambda: step(lambda: net.forward_frames(frames, index)), args.reps)
    print(f"update pass, {n} samples from {len(frames)} distinct frames ({len(frames) / n:.2f} per sample), "
          f"{TORCH_THREADS} threads: whole {1e3 * whole / n:.3f} ms per sample, from distinct frames "
          f"{1e3 * shared / n:.3f}: {shared / whole:.2f}")


if __name__ == "__main__":
    main()
