"""Trained policies and run snapshots in the repository (`policies/`, `results/`) work from any clone: each names
the net it trained on relative to itself, and that net is the one it trained on (the sha256 its run recorded)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from cosim.config import load_config
from cosim.files import file_sha256

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = sorted({p.parent for top in ("policies", "results") for p in (ROOT / top).rglob("*.pt")})


def test_there_are_shipped_policies() -> None:
    assert {"altruistic", "egoistic"} <= {p.name for p in SHIPPED if p.parent.name == "policies"}


@pytest.mark.parametrize("folder", SHIPPED, ids=lambda p: str(p.relative_to(ROOT)))
def test_a_shipped_run_finds_the_net_it_trained_on_from_any_clone(folder: Path) -> None:
    raw = yaml.safe_load((folder / "config.yaml").read_text())["net"]
    assert not Path(raw["file"]).is_absolute(), f"{folder}/config.yaml: net.file {raw['file']} is absolute"
    assert not raw.get("description") or not Path(raw["description"]).is_absolute()
    net = Path(load_config(folder / "config.yaml").net.file)
    assert net.is_file() and net.is_relative_to(ROOT)
    recorded = json.loads((folder / "net.json").read_text())["net"]["sha256"]
    assert file_sha256(net) == recorded
