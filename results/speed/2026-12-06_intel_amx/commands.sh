python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json runs/speed/intel_amx_1.json  # 2026-12-06 07:12-07:14 UTC, quiet
# 2026-12-06 08:48-08:56 UTC, quiet: train.obs_norm off / on alternated twice (logs/bench_ab.sh)
for r in 1 2; do
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json runs/speed/ab_off_$r.json
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --set train.obs_norm=true --json runs/speed/ab_on_$r.json
done
