"""scripts/snapshot_run.py: a run's config written so that a clone of the repository anywhere reads the same paths."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import yaml

from cosim.config import load_config

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("snapshot_run", ROOT / "scripts" / "snapshot_run.py")
snapshot = sys.modules["snapshot_run"] = importlib.util.module_from_spec(spec)
spec.loader.exec_module(snapshot)


def test_a_snapshots_config_names_the_net_and_the_start_relative_to_itself(tmp_path: Path) -> None:
    run = load_config(ROOT / "configs" / "demand.yaml")  # as a run writes it: every path absolute
    assert Path(run.net.file).is_absolute() and Path(run.train.init_from).is_absolute()
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "config.yaml").write_text(yaml.safe_dump(run.to_dict()))
    out = tmp_path / "deep" / "snapshot"
    out.mkdir(parents=True)
    snapshot.portable_config(tmp_path / "run" / "config.yaml", out)
    written = yaml.safe_load((out / "config.yaml").read_text())
    assert not Path(written["net"]["file"]).is_absolute() and not Path(written["train"]["init_from"]).is_absolute()
    again = load_config(out / "config.yaml")
    assert again.net.file == run.net.file and again.train.init_from == run.train.init_from
