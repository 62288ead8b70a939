"""`cosim replay` on real SUMO: a trained policy's episode into a video, the same episode its evaluation played;
live in sumo-gui under Xvfb, the same episode as libsumo's, its screenshot showing the merge area and the
vehicles in their colours; bad input as one line."""

from __future__ import annotations

import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
import yaml
from PIL import Image

from agents.checkpoint import TrainedPolicy, save_checkpoint
from agents.model import ActorCritic
from cosim.cli import main
from cosim.config import load_config
from cosim.environment.render import COLOURS, ROAD
from cosim.evaluation.replay import replay
from cosim.evaluation.runner import Baseline, evaluate
from cosim.files import read_csv
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

SHORT = ["sim.horizon=6"]  # 6 decisions of 10 SUMO steps
SEED = 10_000_000


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A training run folder as `cosim train` leaves it: its resolved config and a (tiny, untrained) policy."""
    run = tmp_path_factory.mktemp("run")
    cfg = load_config("configs/default.yaml", SHORT)
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    o = cfg.observation
    shape = (o.frames, len(o.channels), o.height_px, o.width_px)
    net = ActorCritic(shape, 5, feature_dim=8, head_hidden=8)
    spec = {"agents": [f"av_{i}" for i in range(4)], "obs_shape": list(shape), "obs_dtype": "float32",
            "n_actions": 5, "shared_policy": True, "feature_dim": 8, "head_hidden": 8}
    save_checkpoint(run / "checkpoint.pt", {"spec": spec, "policy": {"nets": [net.state_dict()]},
                                            "counters": {"updates": 1}, "rng": {}})
    return run


def test_replay_of_a_run_is_its_evaluations_episode_on_video(run_dir: Path, tmp_path: Path) -> None:
    assert main(["replay", "--run", str(run_dir), "--seed", str(SEED + 1)]) == 0
    video = run_dir / "replay" / f"video_seed_{SEED + 1}.mp4"
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(video))
    width, height = next(imageio_ffmpeg.read_frames(str(video)))["size"]
    # A frame per SUMO step of the episode (it may end early at a crash: these AVs are untrained) and the first.
    policy = TrainedPolicy(str(run_dir / "checkpoint.pt"))
    row, again = replay(load_config(run_dir / "config.yaml"), policy, SEED + 1, tmp_path / "r")
    assert again is not None and imageio_ffmpeg.count_frames_and_secs(str(again))[0] == frames
    assert 1 < frames <= 1 + 60 and (width, height % 2) == (960, 0)
    # Greedy, as `cosim evaluate` acts: the same episode as the evaluation's of that seed.
    evaluate(load_config(run_dir / "config.yaml"), policy, tmp_path / "ev", episodes=2, seed=SEED, trajectories=0,
             plots=False)
    (evaluated,) = [r for r in read_csv(tmp_path / "ev" / "episodes.csv") if int(r["seed"]) == SEED + 1]
    for key in ("crashed", "merged", "length", "guide_av", "guide_actions"):
        assert str(row[key]) == evaluated[key], key
    assert float(evaluated["merger_distance"]) == pytest.approx(row["merger_distance"])


@pytest.mark.parametrize(("args", "message"), [
    (["--policy", "courteous", "--screenshot", "x.png"], "--screenshot: sumo-gui's view; it needs --gui"),
    (["--policy", "courteous", "--no-video"], "--no-video without --gui: nothing to show"),
    (["--policy", "courteous", "--gui"], "--gui: no display (DISPLAY is unset)"),
    (["--policy", "courteous", "--gui", "--delay", "-1"], "--delay: must be >= 0, got -1.0"),
    (["--seed", "5"], "cosim replay: give --run RUN (or --checkpoint FILE) for a trained policy"),
    (["--policy", "courteous", "--net", "nope.net.xml"], "--net nope.net.xml: not found"),
])
def test_bad_input_is_one_line(args: list[str], message: str, monkeypatch: pytest.MonkeyPatch,
                               caplog: pytest.LogCaptureFixture, tmp_path: Path) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    if "--delay" in args:
        monkeypatch.setenv("DISPLAY", ":99")  # checked before any display is used
    assert main(["replay", *args, "--out", str(tmp_path)]) == 2
    (line,) = caplog.messages
    assert line.startswith(message)
    assert not any(tmp_path.iterdir())


@pytest.fixture(scope="module")
def display() -> Iterator[str]:
    """An Xvfb display of its own for sumo-gui. CI has Xvfb (`.ci/run` installs it): there, without it, the test
    fails; on a user's machine without it (the README's test command as written), it is skipped, saying so."""
    xvfb = shutil.which("Xvfb")
    if xvfb is None:
        why = ("Xvfb not found: sumo-gui needs a display; .ci/run installs it (apt-get install xvfb "
               "libgl1-mesa-dri libglx-mesa0)")
        if os.environ.get("CI"):
            pytest.fail(why)
        pytest.skip(why)
    read, write = os.pipe()
    # -noreset: Xvfb resets when its last client leaves and writes its number to -displayfd again; without a
    # reader that write fails and the server exits (seen here), so the pipe stays open to the end too.
    proc = subprocess.Popen([xvfb, "-displayfd", str(write), "-screen", "0", "1600x1000x24", "-nolisten", "tcp",
                             "-noreset"], pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    os.close(write)
    try:
        number = os.read(read, 16).decode().strip()  # Xvfb writes its display number once it accepts clients
        assert number.isdigit(), f"Xvfb did not start (exit status {proc.poll()})"
        yield f":{number}"
    finally:
        proc.terminate()
        proc.wait(10)
        os.close(read)


def _near(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 12) -> np.ndarray:
    return (np.abs(img.astype(int) - np.asarray(rgb)) <= tol).all(axis=-1)


@pytest.mark.slow  # 9 s; CI, where it must run, runs it with the long tests
def test_sumo_gui_replay_under_xvfb(display: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DISPLAY", display)
    shot = tmp_path / "gui.png"
    cfg = load_config("configs/default.yaml", ["sim.horizon=6"])
    gui_row, gui_video = replay(cfg, Baseline("courteous"), SEED, tmp_path / "gui", gui_delay=0.0, screenshot=shot)
    # sumo-gui over TraCI plays the episode libsumo plays, step for step.
    row, _ = replay(cfg, Baseline("courteous"), SEED, tmp_path / "libsumo", video=False)
    assert {k: gui_row[k] for k in row} == row
    assert gui_video is not None and gui_video.is_file()
    img = np.asarray(Image.open(shot).convert("RGB"))
    assert img.shape[1] >= 800 and img.shape[0] >= 300
    # The merge area: the road in the videos' grey across the view; vehicles in their classes' colours.
    road = _near(img, ROAD)
    assert road.mean() > 0.03 and road.any(axis=0).mean() > 0.9
    # 6 s in, the merging vehicle has just merged among the AVs: all three classes are in view.
    pixels = {kind: int(_near(img, COLOURS[kind], 40).sum()) for kind in (KIND_AV, KIND_HV, KIND_MERGER)}
    assert pixels[KIND_HV] > 4 * 150 and pixels[KIND_AV] > 2 * 150 and pixels[KIND_MERGER] > 100, pixels


def test_cli_replay_with_gui(display: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                             caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level("INFO")
    monkeypatch.setenv("DISPLAY", display)
    shot = tmp_path / "shot.png"
    assert main(["replay", "--policy", "courteous", "--gui", "--delay", "0", "--no-video", "--screenshot", str(shot),
                 "--set", "sim.horizon=2", "--out", str(tmp_path / "out")]) == 0
    assert shot.is_file() and not (tmp_path / "out").exists()
    assert f"courteous seed {SEED}: crash False" in caplog.text and f"wrote screenshot {shot}" in caplog.text
