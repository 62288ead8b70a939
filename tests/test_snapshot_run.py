"""scripts/snapshot_run.py: a run's config written so that a clone of the repository anywhere reads the same paths,
and a run continued from a snapshot joined onto it."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import sys
from pathlib import Path

import pytest
import yaml

from agents.checkpoint import BEST_NAME, POLICY_NAME, first_seed, load_policy, run_record
from agents.train import train
from agents.validation import better
from cosim.config import load_config
from cosim.errors import CosimError
from cosim.files import VALIDATION_LOG, cell_float, read_csv, write_csv

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
@pytest.mark.slow  # 16 s
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
    # The joined run began where its first part did, from scratch, though its second part's config names the start.
    started = Path(load_config(tmp_path / "then" / "config.yaml").train.init_from)
    assert started == (tmp_path / "start" / POLICY_NAME).resolve()
    assert load_config(joined / "config.yaml").train.init_from is None and "init_from" not in run_record(joined)

    # Whichever part validated best gives best.pt: the first part where the second's validations were all worse,
    # the second where the first's were.
    def worst(folder: Path) -> list[dict[str, str]]:
        rows = read_csv(folder / VALIDATION_LOG)
        write_csv(folder / VALIDATION_LOG, [{**r, "crash_high": 100.0} for r in rows])
        return rows

    kept_rows = worst(tmp_path / "then")
    snap(tmp_path / "then", "--continues", tmp_path / "start", "--out", tmp_path / "first_best")
    from_first = load_policy(tmp_path / "first_best" / BEST_NAME)[1]
    assert from_first["counters"] == load_policy(tmp_path / "start" / BEST_NAME)[1]["counters"]
    assert from_first["counters"]["episodes"] <= 8
    write_csv(tmp_path / "then" / VALIDATION_LOG, kept_rows)
    kept_rows = worst(tmp_path / "start")
    snap(tmp_path / "then", "--continues", tmp_path / "start", "--out", tmp_path / "then_best")
    from_then = load_policy(tmp_path / "then_best" / BEST_NAME)[1]
    own = load_policy(tmp_path / "then" / BEST_NAME)[1]
    assert from_then["counters"]["episodes"] == 8 + own["counters"]["episodes"] > 8
    assert from_then["validation"]["episodes"] == 8 + own["validation"]["episodes"]
    write_csv(tmp_path / "start" / VALIDATION_LOG, kept_rows)

    # A third part joins onto the joined snapshot: its counts run on, and it still goes by the first part's seed.
    train(smoke(2003), tmp_path / "third", workers=2, progress=False, init_from=joined / POLICY_NAME)
    snap(tmp_path / "third", "--continues", joined, "--out", tmp_path / "joined3")
    assert [int(r["episodes"]) for r in read_csv(tmp_path / "joined3" / VALIDATION_LOG)] == [4, 8, 12, 16, 20, 24]
    assert load_policy(tmp_path / "joined3" / POLICY_NAME)[1]["counters"]["episodes"] == 24
    assert first_seed(tmp_path / "joined3") == 3
    assert json.loads((tmp_path / "joined3" / "net.json").read_text())["continues"]["before"]["at"]["episodes"] == 8

    # OUT named as the folder a user stands in: staged beside it, not inside it, so its relative paths hold.
    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    snap(tmp_path / "then", "--continues", tmp_path / "start", "--out", ".")
    net = yaml.safe_load((tmp_path / "here" / "config.yaml").read_text())["net"]["file"]
    assert net == os.path.relpath(load_config(joined / "config.yaml").net.file, tmp_path / "here")
    assert sorted(f.name for f in (tmp_path / "here").iterdir()) == sorted(f.name for f in joined.iterdir())

    # A best.pt that the validation log does not pick fails the join after the logs were joined: the earlier
    # snapshot in OUT is left as it was, not half overwritten.
    before = {f.name: f.read_bytes() for f in joined.iterdir()}
    kept_rows = read_csv(tmp_path / "then" / VALIDATION_LOG)
    write_csv(tmp_path / "then" / VALIDATION_LOG, [{**r, "crash_high": 100.0} for r in kept_rows[:-1]]
              + [{**kept_rows[-1], "crash_high": 0.0, "episodes": 7}])
    with pytest.raises(CosimError, match=r"then/best.pt is from episode \d+, not from the validation .* \(episode 7;"):
        snap(tmp_path / "then", "--continues", tmp_path / "start", "--out", joined)
    assert {f.name: f.read_bytes() for f in joined.iterdir()} == before
    assert [f.name for f in tmp_path.iterdir() if f.name.startswith(".")] == []  # no staging left behind
    write_csv(tmp_path / "then" / VALIDATION_LOG, kept_rows)

    # Refused, before anything is written: OUT the start itself, another snapshot than the start, a run of another
    # config, a start without the best.pt its validations promise.
    start_files = {f.name: f.read_bytes() for f in (tmp_path / "start").iterdir()}
    with pytest.raises(CosimError, match=r"--continues .*start and --out name the same folder"):
        snap(tmp_path / "then", "--continues", tmp_path / "start", "--out", tmp_path / "start")
    assert {f.name: f.read_bytes() for f in (tmp_path / "start").iterdir()} == start_files
    with pytest.raises(CosimError, match=r"started from .*start/policy.pt, not from .*first/policy.pt"):
        snap(tmp_path / "then", "--continues", tmp_path / "first", "--out", tmp_path / "wrong")
    other = tmp_path / "other"
    shutil.copytree(tmp_path / "then", other)
    data = yaml.safe_load((other / "config.yaml").read_text())
    data["reward"]["phi"] = 0.0
    (other / "config.yaml").write_text(yaml.safe_dump(data))
    with pytest.raises(CosimError, match=r"another config \(reward.phi differ"):
        snapshot.start_counters(other, tmp_path / "start")
    (tmp_path / "start" / BEST_NAME).unlink()
    with pytest.raises(CosimError, match=r"start has validations but no best.pt to join"):
        snap(tmp_path / "then", "--continues", tmp_path / "start", "--out", tmp_path / "wrong")
    assert not (tmp_path / "wrong").exists()
