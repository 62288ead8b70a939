"""Shared pytest fixtures."""

from __future__ import annotations

from pathlib import Path

import pytest

from sumo_net.build import build_merge_net


@pytest.fixture(scope="session")
def two_lane_net(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 2-lane merge net (80 m acceleration lane) built once per session; returns its .net.xml path."""
    out = tmp_path_factory.mktemp("two_lane_net")
    return build_merge_net(out, lanes=2, accel_length=80, upstream_length=100, downstream_length=500)
