# 2026-12-06 16:13-16:31 UTC, Intel Xeon (Sapphire Rapids), 2 cores, amx_bf16 + avx512_bf16 (bfloat16 auto); quiet
# but for file edits. "before": the parent commit (38ec81c) in a git worktree at /tmp/old, run with PYTHONPATH=/tmp/old;
# "after": this commit's code. Alternated: before 1, after 1, before 2, after 2.
for r in 1 2; do
  (cd /tmp/old && PYTHONPATH=/tmp/old python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json before_$r.json)
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json after_$r.json
done
