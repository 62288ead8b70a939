"""Another library on the env: Stable-Baselines3's PPO trained by scripts/train_sb3.py, evaluated by cosim."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

import cosim
from cosim.errors import ConfigError

pytest.importorskip("stable_baselines3")
pytest.importorskip("supersuit")
from stable_baselines3 import PPO  # noqa: E402 - only where the extra is installed

from agents.sb3 import load_actor  # noqa: E402

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

ROOT = Path(__file__).resolve().parents[2]


# The default run's longest test (40 s on 2 quiet cores, 2026-12-04): in the slow tier, so that the default run stays
# under 10 minutes; the adapter's refusals stay in the default run.
@pytest.mark.slow
def test_sb3_trains_on_the_env_and_its_model_evaluates_like_any_policy(tmp_path: Path) -> None:
    out = tmp_path / "sb3"
    done = subprocess.run([sys.executable, "scripts/train_sb3.py", "--config", "configs/smoke.yaml", "--steps", "2048",
                           "--envs", "2", "--eval-episodes", "2", "--eval-workers", "1", "--out", str(out)],
                          cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert json.loads((out / "eval" / "summary.json").read_text())["episodes"] == 2  # evaluated like any policy
    model = out / "model.zip"
    env = cosim.parallel_env("configs/smoke.yaml")
    shape = env.observation_space(env.possible_agents[0]).shape
    env.close()
    actor = load_actor(model, shape, 5)
    actions = actor.act(np.zeros((3, *shape), np.uint8), greedy=True)
    assert actions.shape == (3,) and set(actions.tolist()) <= set(range(5))
    with pytest.raises(ConfigError, match="trained on observations"):
        load_actor(model, (shape[0] + 1, *shape[1:]), 5)

    ev = subprocess.run([sys.executable, "-m", "cosim.cli", "evaluate", "--config", "configs/smoke.yaml", "--policy",
                         "sb3", "--checkpoint", str(model), "--episodes", "2", "--no-plots", "--out",
                         str(tmp_path / "eval")], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert ev.returncode == 0, ev.stderr[-3000:]
    summary = json.loads((tmp_path / "eval" / "summary.json").read_text())
    assert summary["episodes"] == 2

    # A model retrained into the same file must not resume the evaluation of the old one.
    ppo = PPO.load(model, device="cpu")
    with torch.no_grad():
        next(ppo.policy.parameters()).add_(1.0)
    ppo.save(model)
    ev = subprocess.run([sys.executable, "-m", "cosim.cli", "evaluate", "--config", "configs/smoke.yaml", "--policy",
                         "sb3", "--checkpoint", str(model), "--episodes", "3", "--no-plots", "--out",
                         str(tmp_path / "eval")], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert ev.returncode == 2 and "model_sha256" in ev.stderr and "Traceback" not in ev.stderr

    again = subprocess.run([sys.executable, "scripts/train_sb3.py", "--config", "configs/smoke.yaml",
                            "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert again.returncode == 2 and "holds a model.zip already" in again.stderr and "Traceback" not in again.stderr


def test_a_file_that_is_no_sb3_model_is_one_clear_error(tmp_path: Path) -> None:
    policy = tmp_path / "policy.pt"  # a zip too, as torch.save writes it, but without SB3's data entry
    torch.save({"format": "cosim-policy", "nets": []}, policy)
    with pytest.raises(ConfigError, match=r"policy.pt: a PyTorch file, not a Stable-Baselines3 model; for cosim's "
                                          r"own policy.pt or checkpoint.pt use --policy checkpoint"):
        load_actor(policy, (4, 3, 64, 512), 5)
    text = tmp_path / "model.zip"
    text.write_text("not a zip\n")
    with pytest.raises(ConfigError, match=r"model.zip: not a zip file; --policy sb3 takes a Stable-Baselines3 "
                                          r"model, the .zip that scripts/train_sb3.py saves"):
        load_actor(text, (4, 3, 64, 512), 5)


def test_cosims_own_input_standardisation_is_left_out_of_sb3_by_name_not_silently(
        caplog: pytest.LogCaptureFixture) -> None:
    from agents.config import train_config
    from agents.sb3 import sb3_train_config
    from cosim.config import load_config

    tc = train_config(load_config("configs/default.yaml"))
    assert tc.obs_norm  # the default config's, which scripts/train_sb3.py must still train with
    sb3 = sb3_train_config(tc)
    assert not sb3.obs_norm and sb3.lr == tc.lr and tc.obs_norm
    assert "train.obs_norm: cosim train's input standardisation has no counterpart in SB3's PPO" in caplog.text
    assert tc.egoistic_episodes and not sb3.egoistic_episodes  # the default config's warm-up, left out by name too
    assert "train.egoistic_episodes: cosim train's egoistic warm-up has no counterpart in SB3's PPO" in caplog.text
    caplog.clear()
    sb3_train_config(train_config(load_config(None)))
    assert "obs_norm" not in caplog.text and "egoistic" not in caplog.text and "central" not in caplog.text
    assert not sb3_train_config(train_config({"central_critic": True})).central_critic
    assert "train.central_critic: SB3's PPO here sees each AV as an env of its own" in caplog.text


@pytest.mark.parametrize("feature_norm", [False, True])
def test_sb3s_features_extractor_normalises_its_features_as_the_config_says(feature_norm: bool) -> None:
    import gymnasium

    from agents.config import train_config
    from agents.sb3 import ppo_kwargs

    tc = train_config({"feature_norm": feature_norm})
    policy = ppo_kwargs(tc, n_steps=20, batch=80)["policy_kwargs"]
    space = gymnasium.spaces.Box(0, 255, (2, 4, 8, 16), np.uint8)
    extractor = policy["features_extractor_class"](space, **policy["features_extractor_kwargs"])
    assert any(isinstance(m, torch.nn.LayerNorm) for m in extractor.modules()) is feature_norm
