# 2026-12-07 04:01-05:20 UTC, quiet (nothing else on the machine), 2 cores of an AMD EPYC whose lscpu has avx2 and no
# avx512f, avx512_bf16 or amx_bf16: train.precision auto trains in float32.
# roundK_old_R.json: the parent commit (a5b747f) in a git worktree (PYTHONPATH pointing at it); roundK_new_R.json: this
# commit, each frame through the first layer once; alternated old 1, new 1, old 2, new 2, old 3, new 3 (bench.log).
# Round 1 ran an earlier draft of FrameMemory that selected the acting frames in the (C, H, W) view (a transposing
# copy); rounds 2 and 3 ran this commit's code.
for K in 1 2 3; do for R in 1 2 3; do
  (cd "$OLD" && PYTHONPATH=$OLD python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json round${K}_old_$R.json)
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json round${K}_new_$R.json
done; done
# profile_ppo_before.txt (the parent commit) and profile_a2c_after.txt (this commit): py-spy of the learner,
# inclusive shares of its samples (the run's own setup and the limit's timing included):
py-spy record -f raw -r 50 -- python scripts/bench_train.py --workers 12 --algo ppo --seconds 40 --no-network
py-spy record -f raw -r 50 -- python scripts/bench_train.py --workers 12 --algo a2c --seconds 40 --no-network
# bench_frames.txt: python scripts/bench_frames.py, three times (this commit)
# cosim_bench.txt: cosim bench --episodes 40, then --episodes 200 twice (the parent commit), then --episodes 100 three
# times (this commit; the env's code is the same in both)
