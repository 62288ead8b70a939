#!/bin/bash
# Quiet A/B: acting on one thread while the other half steps (default) vs torch_threads=2 everywhere.
mkdir -p runs/speed  # from the repository root, in its environment
for R in 1 2; do
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json runs/speed/t0_$R.json
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --set train.torch_threads=2 --json runs/speed/t2_$R.json
done
