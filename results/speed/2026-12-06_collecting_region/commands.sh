# 2026-12-06 16:45-17:01 UTC, Intel Xeon (Sapphire Rapids), 2 cores, amx_bf16 + avx512_bf16 (bfloat16 auto); quiet.
# "before": commit bf8281a in a git worktree at /tmp/old (PYTHONPATH=/tmp/old); "after": the same with acting inside
# MultiAgentPolicy.collecting() (autocast's weight cache kept for one update's collection). Alternated, before first.
for r in 1 2; do
  (cd /tmp/old && PYTHONPATH=/tmp/old python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json ppo_a2c_before_$r.json)
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json ppo_a2c_after_$r.json
done
for r in 1 2 3; do
  (cd /tmp/old && PYTHONPATH=/tmp/old python scripts/bench_train.py --workers 12 --algo ppo --seconds 40 --no-network --json ppo_before_$r.json)
  python scripts/bench_train.py --workers 12 --algo ppo --seconds 40 --no-network --json ppo_after_$r.json
done
