"""Time `VelocityMapper.update` on a synthetic scene: a straight 3-lane road of 1.2 km, 5 agents, 25 vehicles.

Prints, per observation preset and dtype, the mean and median `update` time over all 5 agents and the bytes
of one agent's stacked observation; then the two ways of clearing a reused slot (zeroing last time's
written indices, which the mapper does, vs `fill(0)` of the slot and its twin).

Usage: python scripts/bench_velocity_map.py [--steps 400]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

# Run from a checkout without installing: the repository root holds the `cosim` package.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from cosim.config import ObservationConfig  # noqa: E402
from cosim.environment.velocity_map import RoadRaster, VelocityMapper, rasterize_road  # noqa: E402
from cosim.sumo.snapshot import KIND_AV, KIND_HV, KIND_MERGER, Snapshot  # noqa: E402

N_AGENTS, N_VEHICLES, LANE_W, ROAD_LEN = 5, 25, 3.2, 1200.0
DT = 0.1  # [s] between two snapshots: one SUMO step


def make_road() -> RoadRaster:
    xs = np.linspace(0.0, ROAD_LEN, 25)  # many points, as a SUMO lane shape may have
    lanes = [(np.stack([xs, np.full_like(xs, -LANE_W * (k + 0.5))], axis=1), LANE_W) for k in range(3)]
    return rasterize_road(lanes)


def make_snapshots(steps: int, seed: int = 0) -> list[Snapshot]:
    rng = np.random.default_rng(seed)
    kind = np.full(N_VEHICLES, KIND_HV, dtype=np.int8)
    kind[:N_AGENTS] = KIND_AV
    kind[-1] = KIND_MERGER
    x = rng.uniform(50.0, 550.0, N_VEHICLES)
    lane = rng.integers(0, 3, N_VEHICLES)
    y = -LANE_W * (lane + 0.5) + rng.normal(0.0, 0.2, N_VEHICLES)
    heading = rng.normal(0.0, 0.02, N_VEHICLES)
    speed = rng.uniform(20.0, 30.0, N_VEHICLES)
    ids = [f"v{i}" for i in range(N_VEHICLES)]
    snaps = []
    for k in range(steps):
        snaps.append(Snapshot.build(time=k * DT, ids=ids, kind=kind, x=x, y=y, heading=heading, speed=speed))
        x = x + speed * DT
    return snaps


class FillMapper(VelocityMapper):
    """The alternative clearing: `fill(0)` of the whole reused slot and its twin."""

    def _clear_slot(self, t: int) -> None:
        f = self.shape[0]
        self._buf[:, t].fill(0)
        self._buf[:, t + f].fill(0)


def time_updates(mapper: VelocityMapper, snaps: list[Snapshot], rows: np.ndarray) -> np.ndarray:
    for snap in snaps[:20]:  # warm caches and allocator
        mapper.update(snap, rows)
    times = np.empty(len(snaps))
    for i, snap in enumerate(snaps):
        t0 = time.perf_counter()
        mapper.update(snap, rows)
        times[i] = time.perf_counter() - t0
    return times * 1e6  # [us]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=400)
    args = parser.parse_args()
    road = make_road()
    snaps = make_snapshots(args.steps)
    rows = np.arange(N_AGENTS)
    out = [f"road raster {road.grid.shape} cells at {road.resolution} m; "
           f"{N_AGENTS} agents, {N_VEHICLES} vehicles"]
    for preset in ("default", "paper"):
        for dtype in ("float32", "uint8"):
            cfg = ObservationConfig(preset=preset, dtype=dtype)
            mapper = VelocityMapper(cfg, road, N_AGENTS)
            us = time_updates(mapper, snaps, rows)
            nbytes = mapper.observation(0).nbytes
            out.append(f"{preset:8s} {dtype:8s} shape {mapper.shape}: update mean {us.mean():7.1f} us, "
                       f"median {np.median(us):7.1f} us; {nbytes / 1024:8.1f} KiB per observation")
    out.append("clearing a reused slot (float32): written indices vs fill(0) of the slot and its twin")
    for preset in ("default", "paper"):
        cfg = ObservationConfig(preset=preset)
        for name, cls in (("indices", VelocityMapper), ("fill(0)", FillMapper)):
            us = time_updates(cls(cfg, road, N_AGENTS), snaps, rows)
            out.append(f"{preset:8s} {name:8s} update mean {us.mean():7.1f} us, "
                       f"median {np.median(us):7.1f} us")
    print("\n".join(out))  # noqa: T201 - a benchmark's report is its output


if __name__ == "__main__":
    main()
