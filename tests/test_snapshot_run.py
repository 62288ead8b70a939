"""scripts/snapshot_run.py: a run's config written so that a clone of the repository anywhere reads the same paths,
and a run continued from a snapshot joined onto it."""

from __future__ import annotations

import importlib.util
import json
import shutil
import sys
from pathlib import Path

import pytest
import yaml

from agents.checkpoint import BEST_NAME, POLICY_NAME, first_seed, load_policy
from agents.train import train
from agents.validation import better
from cosim.config import load_config
from cosim.errors import CosimError
from cosim.files import VALIDATION_LOG, cell_float, read_csv

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


@pytest.mark.sumo
def test_a_run_continued_from_a_snapshot_joins_it_as_one_run(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # A machine without the first part's run folder goes on with --init-from its snapshot: the joined snapshot's
    # logs, best.pt and counters read as one run, which held-out evaluation and the learning curves take it for.
    def snap(*argv: object) -> None:
        monkeypatch.setattr(sys, "argv", ["snapshot_run.py", *map(str, argv)])
        snapshot.main()

    def smoke(seed: int):
        keys = {"eval_every": 4, "eval_episodes": 3, "episodes": 8, "checkpoint_every": 100, "precision": "float32",
                "seed": seed}
        return load_config(ROOT / "configs" / "smoke.yaml", [f"train.{k}={v}" for k, v in keys.items()])

    train(smoke(3), tmp_path / "first", workers=2, progress=False)
    snap(tmp_path / "first", "--out", tmp_path / "start")
    train(smoke(1003), tmp_path / "then", workers=2, progress=False, init_from=tmp_path / "start" / POLICY_NAME)
    snap(tmp_path / "then", "--continues", tmp_path / "start", "--out", tmp_path / "joined")
    joined = tmp_path / "joined"

    updates = read_csv(joined / "updates.csv")
    assert [int(r["update"]) for r in updates] == list(range(1, len(updates) + 1))
    assert int(updates[-1]["episodes"]) == 16 and float(updates[-1]["train_s"]) > float(updates[0]["train_s"])
    episodes = read_csv(joined / "episodes.csv.gz")
    assert [int(r["episode"]) for r in episodes] == list(range(1, 17))
    validation = read_csv(joined / VALIDATION_LOG)
    assert [int(r["episodes"]) for r in validation] == [4, 8, 12, 16]
    best = None  # the marks training would have made over both parts
    for row in validation:
        fig = {k: cell_float(v) for k, v in row.items()}
        assert int(row["best"]) == int(better(fig, best))
        best = fig if int(row["best"]) else best
    kept = load_policy(joined / BEST_NAME)[1]
    assert kept["counters"]["episodes"] == best["episodes"] and kept["validation"]["crash_high"] == best["crash_high"]
    assert load_policy(joined / POLICY_NAME)[1]["counters"]["episodes"] == 16
    record = json.loads((joined / "net.json").read_text())["continues"]
    assert record["at"]["episodes"] == 8 and record["train_seed"] == 3
    assert first_seed(joined) == 3 and first_seed(tmp_path / "then") is None  # held out, it goes by seed 3
    assert (joined / record["snapshot"]).resolve() == (tmp_path / "start").resolve()

    # Refused, before anything is written: another snapshot than the start, and a run of another config.
    with pytest.raises(CosimError, match=r"started from .*start/policy.pt, not from .*first/policy.pt"):
        snap(tmp_path / "then", "--continues", tmp_path / "first", "--out", tmp_path / "wrong")
    other = tmp_path / "other"
    shutil.copytree(tmp_path / "then", other)
    data = yaml.safe_load((other / "config.yaml").read_text())
    data["reward"]["phi"] = 0.0
    (other / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(CosimError, match=r"another config \(reward.phi differ"):
        snapshot.start_counters(other, tmp_path / "start")
    assert not (tmp_path / "wrong").exists()
