#!/bin/bash
# 2026-12-07 11:17-11:21 UTC, 2 cores of an AMD EPYC with avx2 and no AVX-512, quiet (nothing else running).
# <parent> is a git worktree of 36161fc (`git worktree add -f <parent> 36161fc`), run with PYTHONPATH=<parent>.
#
# ab_env_code.txt: the env's code before (36161fc, with this commit's cosim/bench.py copied in, so both sides are
# measured the same way) and after, alternated four times:
#   (cd <side> && PYTHONPATH=<side> python -m cosim.cli bench --episodes 100)
# ab_method.txt: 36161fc's own cosim bench (the env's episodes, then the bare loops one after the other) alternated
# with this commit's (each episode replayed by the bare loops at once), three times, the same command.
#
# share_R.json: the learner's share of the machine's limit at this commit, 11:50-12:00 UTC, quiet, R = 1..4 one
# after the other:
#   python scripts/bench_train.py --workers 12 --algo ppo a2c --seconds 40 --no-network --json share_R.json
