# 2026-12-07 01:03-01:46 UTC, quiet, 2 cores of an AMD EPYC; lscpu | grep -o 'avx512_bf16\|amx_bf16' prints
# avx512_bf16 only, so train.precision auto trains in bfloat16.
# head_0103.json: the parent commit (9b93b1b) alone, before any change:
python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json head_0103.json
# old_R.json: the parent commit in a git worktree (PYTHONPATH pointing at it), new_R.json: this commit;
# alternated old 1, new 1, old 2, new 2, ... (bench.log). old_3's bare loop was timed while a micro-benchmark
# ran beside it (1.883 ms per decision against 1.02-1.26 in the other runs), so its limit and share are off;
# its rates were measured quiet.
for R in 1 2 3 4; do
  (cd "$OLD" && PYTHONPATH=$OLD python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json old_$R.json)
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json new_$R.json
done
# cosim_bench.txt: this commit alone
cosim bench --episodes 40
