"""`cosim replay`: one episode of a policy as a person watches it, live in sumo-gui and into a video.

Contract: `replay(cfg, policy, seed, out_dir, video, gui_delay, screenshot)` plays episode `seed` with `policy`
(a `cosim.evaluation.runner.Policy`: a baseline or a trained policy, loaded and run by the evaluation's own
`Runner`, so it acts as in `cosim evaluate` and plays the same episode as an evaluation of that seed). With
`gui_delay` it runs in sumo-gui over TraCI (`gui_view`: the merge area, vehicles in the videos' colours, each
AV's action beside it), pausing that many ms per SUMO step; with `screenshot` it saves sumo-gui's view there
after the episode. With `video` it writes `out_dir/video_seed_S.mp4` (or `.gif` without an ffmpeg:
`cosim.evaluation.video`). Returns the episode's row (the evaluation's `episodes.csv` columns) and the video.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from cosim.config import Config, load_config
from cosim.environment.merge_env import MergeEnv
from cosim.environment.render import COLOURS
from cosim.evaluation.plots import CRASHED_RGB
from cosim.evaluation.runner import Job, Policy, Runner
from cosim.evaluation.video import merge_area
from cosim.sumo.net import Net, load_net
from cosim.sumo.session import Gui


def gui_view(net: Net, delay: float = 0.0) -> Gui:
    """sumo-gui showing what the videos show: the merge area, vehicles in the top views' colours."""
    return Gui(view=merge_area(net), colours=COLOURS, crashed=CRASHED_RGB, delay=delay)


def replay(cfg: Config, policy: Policy, seed: int, out_dir: Path, video: bool = True, gui_delay: float | None = None,
           screenshot: Path | None = None) -> tuple[dict[str, Any], Path | None]:
    # No SUMO outputs: they would run the episode on to the horizon and close sumo-gui before the screenshot.
    cfg = load_config(cfg, {**policy.overrides, "sim.outputs": False})
    gui = None if gui_delay is None else gui_view(load_net(cfg.net.file, cfg.net.description), gui_delay)
    job = Job(cfg.to_dict(), policy, str(out_dir), frozenset(), frozenset({seed} if video else ()), str(out_dir))
    runner = Runner(job, MergeEnv(cfg, gui=gui))
    try:
        row = runner.run(seed)
        if screenshot is not None:
            Path(screenshot).parent.mkdir(parents=True, exist_ok=True)
            runner.env.session.screenshot(screenshot)
    finally:
        runner.close()
    return row, runner.video
