# 2026-12-07 07:15-07:50 UTC, quiet (nothing else on the machine), 2 cores of an AMD EPYC whose lscpu has avx2 and no
# avx512f, avx512_bf16 or amx_bf16: train.precision auto trains in float32.
# old_R.json: the parent commit (58362b2, each frame through the first layer once) in a git worktree (PYTHONPATH
# pointing at it); new_R.json: the second layer by depth taps, alternated old 1, new 1, old 2, new 2, ... (bench.log).
# The "new" side ran a draft of this commit whose FrameMemory gathered each slot's frame features into a stack per call
# (a copy of every stack) where this commit reads them in place from a ring per slot, and whose ActorCritic.value ran
# both encoders where the critic has its own (not the default); final_R.json: this commit, run twice after the A/B.
for R in 1 2 3 4 5 6; do
  (cd "$OLD" && PYTHONPATH=$OLD python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json old_$R.json)
  python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json new_$R.json
done
for R in 1 2; do python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json final_$R.json; done
# profile_ppo_taps.txt: py-spy of the learner (the draft), inclusive shares of its samples (setup and the limit's timing
# included), 07:09 UTC:
py-spy record -f raw -r 50 -- python scripts/bench_train.py --workers 12 --algo ppo --seconds 40 --no-network
# bench_frames.txt: python scripts/bench_frames.py; cosim_bench.txt: cosim bench --episodes 100
