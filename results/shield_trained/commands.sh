# 2026-12-07, AMD EPYC, 2 cores, avx2 without AVX-512 (float32). Two training runs side by side each time.
# Trained (13:59-14:28 UTC the seed 102 pair; 14:33-15:02 UTC the seed 103 pair, 1,570-1,750 s of training each):
cosim train --set reward.phi=0.7854 --set train.seed=102 --set av.shield=sumo --set train.eval_every=500 --set train.torch_threads=1 --episodes 2004 --out runs/learner/shield_pi4_s102
cosim train --set reward.phi=0 --set train.seed=102 --set av.shield=sumo --set train.eval_every=500 --set train.torch_threads=1 --episodes 2004 --out runs/learner/shield_phi0_s102
cosim train --set reward.phi=0.7854 --set train.seed=103 --set av.shield=sumo --set train.eval_every=500 --set train.torch_threads=1 --episodes 2004 --out runs/learner/shield_pi4_s103
cosim train --set reward.phi=0.7854 --set train.seed=103 --set train.eval_every=500 --set train.torch_threads=1 --episodes 2004 --out runs/learner/d504_pi4_s103
# (runs/learner/d504_pi4_s102: the same without the shield, docs/results.md "The entropy bonus annealed to zero")
# Played with and without the shield, 200 evaluation episodes each (10,000,000 on), alone on the machine:
# first the seed-102 runs (14:28-14:33 UTC, 265 s), then all five (the first ten folders resumed; 15:02-15:05, 143 s)
python scripts/shield.py --runs runs/learner/d504_pi4_s102 runs/learner/shield_pi4_s102 runs/learner/shield_phi0_s102 --episodes 200 --out runs/shield_trained
python scripts/shield.py --runs runs/learner/d504_pi4_s102 runs/learner/shield_pi4_s102 runs/learner/shield_phi0_s102 runs/learner/d504_pi4_s103 runs/learner/shield_pi4_s103 --episodes 200 --out runs/shield_trained
# Episodes to the criterion, each run against the courteous rule in its own setting:
python scripts/episodes_to_criterion.py runs/learner/d504_pi4_s102 runs/learner/d504_pi4_s103 runs/learner/shield_pi4_s102 runs/learner/shield_pi4_s103 runs/learner/shield_phi0_s102 --workers 2 --out runs/shield_criterion
