"""Episode videos on real SUMO: a frame per SUMO step, labelled with the time, the AVs' actions and the merging
vehicle's state; the episode is the same with a video as without; MP4 with an ffmpeg, GIF without."""

from __future__ import annotations

from pathlib import Path

import imageio_ffmpeg
import numpy as np
import pytest
from PIL import Image

from cosim.config import load_config
from cosim.environment.merge_env import MergeEnv
from cosim.environment.policies import POLICIES
from cosim.evaluation import video
from cosim.evaluation.video import ACTION_NAMES, EpisodeView

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

SEED = 10_000_000  # a courteous episode of the default scenario in which the merging vehicle gets in


def _play(env: MergeEnv, policy: str, view: EpisodeView | None) -> tuple[dict, list[dict[str, int]]]:
    act = POLICIES[policy](SEED)
    env.reset(seed=SEED)
    if view is not None:
        view.start()
    decisions, infos = [], {}
    while env.agents:
        actions = act(env)
        decisions.append(actions)
        if view is not None:
            view.decide(actions)
        _, _, _, _, infos = env.step(actions)
    if view is not None:
        view.stop()
    return next(iter(infos.values()))["episode"], decisions


@pytest.fixture(scope="module")
def courteous() -> tuple[EpisodeView, list[dict[str, int]], dict]:
    env = MergeEnv(load_config("configs/default.yaml", ["sim.horizon=10"]))
    try:
        view = EpisodeView(env)
        summary, decisions = _play(env, "courteous", view)
    finally:
        env.close()  # writing the video needs the net, not SUMO: another test may start its own
    return view, decisions, summary


def test_a_frame_per_step_labelled_with_time_actions_and_the_merging_vehicle(courteous) -> None:
    view, decisions, summary = courteous
    assert summary["merged"] and not summary["crashed"]
    # 10 decisions of 10 SUMO steps of 0.1 s, and the frame at the reset: real time at 10 fps.
    assert view.fps == 10.0 and len(view.frames) == 1 + 10 * 10 == 1 + 10 * len(decisions)
    times = [f.snap.time for f in view.frames]
    assert times == pytest.approx([times[0] + 0.1 * k for k in range(len(times))])
    assert view.frames[0].actions == {}  # before the first decision
    for k, frame in enumerate(view.frames[1:]):  # frames 1-10 show decision 0's actions, 11-20 decision 1's, ...
        assert frame.actions == {a: ACTION_NAMES[int(v)] for a, v in decisions[k // 10].items()}
    # This merging vehicle enters the acceleration lane, then the gap the AVs opened.
    assert _states(view) == ["on the ramp", "on the acceleration lane", "merged"]
    assert view.frames[-1].merger.endswith(" m/s")


def _states(view: EpisodeView) -> list[str]:
    """The merging vehicle's states, in the order it went through them."""
    states = [f.merger.split(",")[0] for f in view.frames]
    return [s for i, s in enumerate(states) if i == 0 or s != states[i - 1]]


def test_the_episode_is_the_same_with_a_video(courteous) -> None:
    # These idle AVs crash into slower vehicles at the 18th decision: the video's reads between decisions must
    # not take the collision from the env's snapshots.
    env = MergeEnv(load_config("configs/default.yaml"))
    try:
        without, _ = _play(env, "idle", None)
        view = EpisodeView(env)
        with_video, _ = _play(env, "idle", view)
    finally:
        env.close()
    assert without["crashed"] and without["ended_by"] == "collision" and with_video == without
    # Frames up to the SUMO step of the collision, the wrecks marked in the last one only.
    first, last = view.frames[0].snap.time, view.frames[-1].snap.time
    assert len(view.frames) == round((last - first) / 0.1) + 1 < 1 + 200
    assert [bool(f.snap.crashed.any()) for f in view.frames[-2:]] == [False, True]
    # The legend names the crashed colour where a frame shows a wreck, and only there.
    assert view.shows_crash and not courteous[0].shows_crash
    for crashed in (True, False):
        labels = [t.get_text() for t in video._FrameRenderer(env, (0.0, 200.0), "", crashed).fig.legends[0].texts]
        assert ("crashed" in labels) is crashed and "AV" in labels
    states = _states(view)  # it waits at the lane's end, crawling forward now and then, and never gets in
    assert states[:3] == ["on the ramp", "on the acceleration lane", "stuck at the end of the acceleration lane"]
    assert "merged" not in states


def test_mp4_with_ffmpeg_gif_without(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    env = MergeEnv(load_config("configs/default.yaml", ["sim.horizon=3"]))  # short: 50 ms to draw a frame
    try:
        view = EpisodeView(env)
        _play(env, "courteous", view)
    finally:
        env.close()
    assert len(view.frames) == 31
    mp4 = view.write(tmp_path / "episode", title="courteous")
    assert mp4 == tmp_path / "episode.mp4"
    frames, _ = imageio_ffmpeg.count_frames_and_secs(str(mp4))
    meta = next(imageio_ffmpeg.read_frames(str(mp4)))
    width, height = meta["size"]
    assert frames == len(view.frames) and meta["fps"] == 10.0
    assert width == 960 and height % 2 == 0 and 150 < height < 400
    assert 20_000 < mp4.stat().st_size < 2_000_000
    # The road has its lane markings: between the first and last rows of the dark background around the road,
    # rows mostly of light paint (a solid side line) and rows a quarter painted (a dashed line between lanes).
    reader = imageio_ffmpeg.read_frames(str(mp4))
    next(reader)  # the metadata
    frame = np.frombuffer(next(reader), np.uint8).reshape(height, width, 3)
    reader.close()
    around = np.flatnonzero((frame < 50).all(axis=-1).mean(axis=1) > 0.2)
    paint = (frame[around[0]: around[-1] + 1] > 200).all(axis=-1).mean(axis=1)  # (rows,) share of light pixels
    assert paint.max() > 0.9 and ((paint > 0.2) & (paint < 0.3)).any()
    monkeypatch.setattr(video, "find_ffmpeg", lambda: None)
    gif = view.write(tmp_path / "episode", title="courteous")
    assert gif == tmp_path / "episode.gif"
    with Image.open(gif) as img:
        assert img.n_frames == len(view.frames) and img.size == (width, height) and img.info["duration"] == 100
