"""What a person sees of an episode: its video, and the AVs' actions in sumo-gui.

Contract: `EpisodeView(env, video=True)` watches one episode of a `MergeEnv`: `start()` after `env.reset`,
`decide(actions)` before each `env.step` (the live agents' actions), `stop()` after the last step. With
`video`, it keeps a frame at every `frame_period` [s] of simulation time (every SUMO step of the episode's
decisions, through the session's `on_step`; default 0.1 s, so the video plays in real time at 10 fps) and
`write(path)` encodes them: the top view of `merge_area` (`cosim.environment.render.top_view`, the renderer
of the env and of the evaluation's top views; the road with its lane markings drawn once per video) with AVs,
HVs and the merging vehicle in their class's colour
and crashed vehicles red, each AV numbered, and above it the time, each AV's action and the merging
vehicle's state (`merger_state`). MP4 (H.264) where an ffmpeg is found (imageio-ffmpeg's, from the `replay`
extra, or one on PATH), else GIF (Pillow, matplotlib's own dependency): the suffix of the path written says
which. With a session on sumo-gui (`cosim.sumo.session.Gui`), `decide` also writes each AV's action beside
it there (`SumoSession.label`).
"""

from __future__ import annotations

import logging
import math
import shutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib import animation, rc_context
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patheffects import withStroke

from cosim.environment.control import Action
from cosim.environment.episode import MergeZone, merge_status
from cosim.environment.merge_env import MergeEnv
from cosim.environment.render import COLOURS, draw_vehicles, lane_markings, road_view
from cosim.evaluation.plots import CRASHED_RGB, class_legend
from cosim.files import atomic_path
from cosim.sumo.net import Net
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Snapshot

log = logging.getLogger(__name__)

ACTION_NAMES = {int(a): a.name.lower().replace("_", " ") for a in Action}
SUMO_DRIVES = "SUMO drives"  # the label of AVs that SUMO's models drive (the `sumo` baseline)
WIDTH_PX = 960  # video frame width; H.264 wants even sizes
DPI = 100


def merge_area(net: Net, upstream: float = 100.0, downstream: float = 50.0, margin: float = 15.0
               ) -> tuple[float, float, float, float]:
    """[m] (x0, y0, x1, y1) in network coordinates: the merge edge's lanes, `upstream` before and `downstream`
    beyond them along x, `margin` across: what the videos and sumo-gui show."""
    shapes = np.concatenate([lane.shape for lane in net.road.edges[net.desc.merge_edge].lanes])
    (x0, y0), (x1, y1) = shapes.min(axis=0), shapes.max(axis=0)
    return x0 - upstream, y0 - margin, x1 + downstream, y1 + margin


def merger_state(snap: Snapshot, zone: MergeZone, merged_before: bool, stuck_speed: float,
                 stuck_distance: float) -> str:
    """The merging vehicle's state in words: not yet on the road, on the ramp, on the acceleration lane, stuck
    at its end, merged, crashed, or gone (left the net after merging)."""
    status = merge_status(snap, zone, stuck_speed, stuck_distance)
    if status.row < 0:
        return "left the net" if merged_before else "not on the road"
    if status.crashed:
        return "crashed"
    if status.merged or merged_before:
        return "merged"
    if status.stuck:
        return "stuck at the end of the acceleration lane"
    r = status.row
    if snap.edge[r] == zone.merge_edge and int(snap.lane[r]) in zone.accel_lanes:
        return "on the acceleration lane"
    return "on the ramp"


@dataclass(frozen=True)
class Frame:
    snap: Snapshot  # `SumoSession.view()`: crashed = in a collision so far
    actions: Mapping[str, str]  # live AV -> its action's name
    merger: str  # merger_state, with its speed


class EpisodeView:
    """One episode as a person sees it (module doc)."""

    def __init__(self, env: MergeEnv, video: bool = True, frame_period: float = 0.1) -> None:
        self.env = env
        self.video = video
        step = env.cfg.sim.step_length
        self.steps_per_frame = max(1, round(frame_period / step))
        self.fps = 1.0 / (self.steps_per_frame * step)
        self.frames: list[Frame] = []
        self._actions: dict[str, str] = {}
        self._merged = False
        self._steps = 0

    def start(self) -> None:
        """After `env.reset`: the first frame, then one every `steps_per_frame` SUMO steps."""
        self.frames.clear()
        self._actions, self._merged, self._steps = {}, False, 0
        if self.video:
            self.env.session.on_step = self._on_step
            self._frame()

    def decide(self, actions: Mapping[str, int]) -> None:
        """Before `env.step(actions)`: the actions the frames (and sumo-gui) show until the next decision."""
        session = self.env.session
        self._actions = {a: ACTION_NAMES[int(v)] if session.drive_avs else SUMO_DRIVES for a, v in actions.items()}
        for agent, name in self._actions.items():
            session.label(agent, f"{agent} {name}")

    def stop(self) -> None:
        if self.env.session.on_step == self._on_step:
            self.env.session.on_step = None

    def _on_step(self) -> None:
        self._steps += 1
        if self._steps % self.steps_per_frame == 0:
            self._frame()

    def _frame(self) -> None:
        env = self.env
        snap = env.session.view()
        sim = env.cfg.sim
        state = merger_state(snap, env.zone, self._merged, sim.stuck_speed, sim.stuck_distance)
        self._merged |= state == "merged"
        row = np.flatnonzero(snap.kind == KIND_MERGER)
        speed = f", {snap.speed[row[0]]:.1f} m/s" if row.size else ""
        self.frames.append(Frame(snap, dict(self._actions), state + speed))

    @property
    def shows_crash(self) -> bool:
        """Whether a frame shows a crashed vehicle (the video's legend names the colour only then)."""
        return any(frame.snap.crashed.any() for frame in self.frames)

    def write(self, path: Path, title: str = "") -> Path:
        """Encode the frames into `path` with the suffix of the format written (.mp4, or .gif without an
        ffmpeg); returns the path written."""
        if not self.frames:
            raise ValueError("no frames: call start() after env.reset and step the episode")
        ffmpeg = find_ffmpeg()
        path = Path(path).with_suffix(".mp4" if ffmpeg else ".gif")
        x0, _, x1, _ = merge_area(self.env.net)
        renderer = _FrameRenderer(self.env, (x0, x1), title, self.shows_crash)
        if ffmpeg:
            writer: animation.AbstractMovieWriter = animation.FFMpegWriter(
                fps=self.fps, codec="libx264", extra_args=["-pix_fmt", "yuv420p", "-crf", "26"])
        else:
            log.info("no ffmpeg (pip install -e \".[replay]\" brings one): writing %s as a GIF", path.name)
            writer = animation.PillowWriter(fps=self.fps)
        logging.getLogger("matplotlib.animation").setLevel(logging.WARNING)  # not ffmpeg's command line per video
        with (rc_context({"animation.ffmpeg_path": ffmpeg or "ffmpeg"}), atomic_path(path) as tmp,
              writer.saving(renderer.fig, tmp, DPI)):  # an interrupted video leaves no half file
            for frame in self.frames:
                renderer.draw(frame)
                writer.grab_frame()
        return path


def find_ffmpeg() -> str | None:
    """The ffmpeg that MP4s are encoded with: imageio-ffmpeg's (the `replay` extra), else one on PATH."""
    try:
        import imageio_ffmpeg
    except ImportError:
        return shutil.which("ffmpeg")
    return imageio_ffmpeg.get_ffmpeg_exe()


class _FrameRenderer:
    """One figure, redrawn per frame: the header (time, actions, merging vehicle) above the top view."""

    HEADER_PX, FOOTER_PX, ABOVE_M = 60, 22, 8.0  # text above and below the view; road above it for AV numbers

    def __init__(self, env: MergeEnv, x_range: tuple[float, float], title: str, crashed: bool) -> None:
        """`crashed`: some frame shows a crashed vehicle (the legend names the colour only then)."""
        self.title = title
        self.agents = env.possible_agents
        # The road and its lane markings once per video; each frame draws its vehicles on a copy.
        self.road, self.extent = road_view(env.road_raster, x_range, lane_markings(env.net.road))
        x0, x1, y0, y1 = self.extent
        view_px = WIDTH_PX * (y1 - y0 + self.ABOVE_M) / (x1 - x0)
        height_px = 2 * math.ceil((self.HEADER_PX + view_px + self.FOOTER_PX) / 2)
        self.fig = Figure(figsize=(WIDTH_PX / DPI, height_px / DPI), dpi=DPI, facecolor="white")
        FigureCanvasAgg(self.fig)
        bottom = self.FOOTER_PX / height_px
        self.ax = self.fig.add_axes((0.0, bottom, 1.0, view_px / height_px))
        self.ax.set_axis_off()
        self.image = self.ax.imshow(self.road, extent=self.extent, interpolation="nearest", aspect="equal")
        self.ax.set_xlim(x0, x1)
        self.ax.set_ylim(y0, y1 + self.ABOVE_M)
        self.header = self.fig.text(0.01, 1 - 4 / height_px, "", va="top", ha="left", fontsize=9, family="monospace")
        self.fig.legend(*class_legend(guide=False, crashed=crashed), loc="lower right", ncols=4, fontsize=7,
                        frameon=False, bbox_to_anchor=(1.0, 0.0))
        self.fig.text(0.01, 0.01, f"top view to scale, x {x0:.0f}-{x1:.0f} m (SUMO network coordinates); "
                      "numbers: the AVs", fontsize=7, va="bottom")
        self.numbers: list = []
    def draw(self, frame: Frame) -> None:
        s = frame.snap
        colours = np.array([CRASHED_RGB if c else COLOURS.get(int(k), COLOURS[KIND_HV])
                            for k, c in zip(s.kind, s.crashed, strict=True)], dtype=np.uint8).reshape(-1, 3)
        img = self.road.copy()
        draw_vehicles(img, self.extent, s.x, s.y, s.heading, s.length, s.width, colours)
        self.image.set_data(img)
        for t in self.numbers:
            t.remove()
        rows = np.flatnonzero(s.kind == KIND_AV)
        self.numbers = [self.ax.text(s.x[r], s.y[r] + s.width[r], s.ids[r].rsplit("_", 1)[-1], color="black",
                                     fontsize=8, fontweight="bold", ha="center", va="bottom", clip_on=True,
                                     path_effects=[withStroke(linewidth=2.5, foreground="white")]) for r in rows]
        actions = "  ".join(f"{a}: {self._action(frame, a)}" for a in self.agents)
        self.header.set_text(f"{self.title}{'  ' if self.title else ''}t = {s.time:5.1f} s\n"
                             f"AV actions  {actions}\nmerging vehicle: {frame.merger}")

    @staticmethod
    def _action(frame: Frame, agent: str) -> str:
        row = frame.snap.row_of(agent)
        if row < 0:
            return "gone"  # off the net (or taken off after a crash)
        if frame.snap.crashed[row]:
            return "crashed"
        return frame.actions.get(agent, "-")  # "-": before the first decision
