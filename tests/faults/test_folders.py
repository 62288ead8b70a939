"""Run and evaluation folders through the `cosim` command: one writer per folder (a second command gets one line
and exit 2 while the first lives; a `kill -9`ed one leaves the folder free), a stop that names only a checkpoint
that is there, and `compare` / `--resume` checking a folder's files against each other (real SUMO, smoke config)."""

from __future__ import annotations

import copy
import os
import re
import shutil
import signal
import time
from pathlib import Path
from typing import Any

import pytest
import torch

from agents.checkpoint import read_checkpoint
from cosim.files import LOCK_NAME, read_csv

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo)

SMOKE = Path(__file__).resolve().parents[2] / "configs" / "smoke.yaml"


def _same_tensors(a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same_tensors(a[k], b[k]) for k in a)
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same_tensors(x, y) for x, y in zip(a, b, strict=True))
    return torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b


# -- one writer per folder -------------------------------------------------------------------------------
@pytest.mark.slow  # over 10 s: CI runs it with the long tests
def test_a_second_trainer_into_a_live_run_folder_is_refused_and_a_killed_one_leaves_it_free(cli: Any) -> None:
    # No checkpoint before the kill: neither by the updates' count nor after a validation.
    first = cli.start("train", "--config", cli.SMOKE, "--out", "run",
                      *cli.settings("train.episodes=400", "train.checkpoint_every=1000", "train.eval_every=0"))
    try:
        cli.wait_for(first, "update 1,")
        busy = f"run: in use by another cosim process (pid {first.pid}, cosim train); wait for it to finish"
        cli.assert_clean_error(cli.run("train", "--config", cli.SMOKE, "--out", "run", "--resume"), busy)
    finally:
        first.kill()  # kill -9: the lock is the kernel's to drop
        first.wait()
    # Free: the next command gets past the lock to the folder's own state (no checkpoint was written).
    cli.assert_clean_error(cli.run("train", "--config", cli.SMOKE, "--out", "run", "--resume"),
                           "checkpoint run/checkpoint.pt: not found")
    assert not (cli.folder / "run" / LOCK_NAME).exists()


def test_a_second_evaluation_into_a_live_folder_is_refused_and_a_killed_one_leaves_it_free(cli: Any) -> None:
    first = cli.start("evaluate", "--config", cli.SMOKE, "--policy", "idle", "--episodes", "5000", "--out", "ev")
    try:
        cli.wait_for(first, "1 of 5000 episodes")
        proc = cli.run("evaluate", "--config", cli.SMOKE, "--policy", "idle", "--episodes", "2", "--out", "ev")
        cli.assert_clean_error(proc, f"ev: in use by another cosim process (pid {first.pid}, cosim evaluate)")
    finally:
        first.kill()
        first.wait()
    proc = cli.run("evaluate", "--config", cli.SMOKE, "--policy", "idle", "--episodes", "2", "--out", "ev",
                   "--no-plots")
    assert proc.returncode == 0, proc.stderr
    assert len(read_csv(cli.folder / "ev" / "episodes.csv")) >= 2


def test_a_second_sweep_into_a_live_sweep_folder_is_refused(cli: Any) -> None:
    args = ("sweep", "--config", cli.SMOKE, "--phi", "0", "--seeds", "0", "--budget-min", "0.05",
            "--eval-episodes", "50", "--eval-workers", "1", "--baselines", "idle", "--out", "sweep")
    first = cli.start(*args)
    try:
        deadline = time.monotonic() + 120
        while not (cli.folder / "sweep" / LOCK_NAME).is_file() and first.poll() is None:
            assert time.monotonic() < deadline, "the first sweep took no lock"
            time.sleep(0.2)
        cli.assert_clean_error(cli.run(*args), f"in use by another cosim process (pid {first.pid}, cosim sweep)")
    finally:
        first.kill()
        first.wait()


# -- a stop names only a checkpoint that is there -----------------------------------------------------------
def _checkpoints_named(out: str) -> list[str]:
    return re.findall(r"[\w./-]*checkpoint\.pt", out)


@pytest.mark.slow  # over 10 s: CI runs it with the long tests
def test_two_ctrl_c_before_the_first_checkpoint_leave_a_checkpoint_that_resumes(cli: Any, tmp_path: Path) -> None:
    # Where the second Ctrl-C lands (collecting or learning) is the machine's doing: the next test places it.
    proc = cli.start("train", "--config", cli.SMOKE, "--out", "run", *cli.settings("train.episodes=400",
                                                                                    "train.log_every_s=0"))
    cli.wait_for(proc, "update 1,")  # update 2 of 4 before the first checkpoint is under way
    proc.send_signal(signal.SIGINT)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    out = cli.finish(proc)
    assert proc.returncode == 130 and "Traceback" not in out, out
    named = _checkpoints_named(out)
    assert named and all((tmp_path / p).is_file() for p in named), out
    counters = read_checkpoint(tmp_path / "run" / "checkpoint.pt")["counters"]
    assert f"trained {counters['episodes']} episodes ({counters['updates']} updates" in out, out
    assert len(read_csv(tmp_path / "run" / "episodes.csv")) == counters["episodes"]  # the log is the checkpoint's
    proc = cli.run("train", "--config", cli.SMOKE, "--out", "run", "--resume",
                   *cli.settings(f"train.episodes={counters['episodes']}", "train.log_every_s=0"))
    assert proc.returncode == 0, proc.stderr
    assert f"resumed run/checkpoint.pt at update {counters['updates']}" in proc.stderr


def test_a_second_ctrl_c_while_learning_checkpoints_the_last_complete_update_exactly(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    import agents.train
    from agents.checkpoint import rng_state
    from agents.multiagent import MultiAgentPolicy
    from cosim.config import load_config

    real_collect, real_update, before = agents.train.collect, MultiAgentPolicy.update, {}

    def collect(pool: Any, policy: MultiAgentPolicy, batch: Any, seeds: list[int], k: int, egoistic: bool) -> Any:
        if k == 1:  # the second update, before the first checkpoint (every 4), as it begins
            before.update(policy=copy.deepcopy(policy.state_dict()), rng=rng_state())
        return real_collect(pool, policy, batch, seeds, k, egoistic)

    def update(self: MultiAgentPolicy, batch: Any, tc: Any, k: int, progress: float) -> dict[str, float]:
        stats = real_update(self, batch, tc, k, progress)
        if k == 1:  # its parameters changed, its counters not yet: Ctrl-C twice, as a user would
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
        return stats

    monkeypatch.setattr(agents.train, "collect", collect)
    monkeypatch.setattr(MultiAgentPolicy, "update", update)
    result = agents.train.train(load_config(SMOKE), tmp_path / "run", episodes=400, progress=False)
    assert result.interrupted and (result.updates, result.episodes) == (1, 2)
    saved = read_checkpoint(tmp_path / "run" / "checkpoint.pt")
    assert (saved["counters"]["updates"], saved["counters"]["episodes"]) == (1, 2)
    assert _same_tensors(saved["policy"], before["policy"])  # exactly the state before the cut update
    assert _same_tensors(saved["rng"], before["rng"])  # and the RNG states it began with: a resume replays it
    assert [int(r["episode"]) for r in read_csv(tmp_path / "run" / "episodes.csv")] == [1, 2]


# -- compare checks an evaluation's files against each other ------------------------------------------------
@pytest.fixture(scope="module")
def evaluation(tmp_path_factory: pytest.TempPathFactory, cli_class: type) -> Path:
    """A finished 3-episode evaluation of the idle baseline."""
    tmp = tmp_path_factory.mktemp("evaluation")
    proc = cli_class(tmp).run("evaluate", "--config", cli_class.SMOKE, "--policy", "idle", "--episodes", "3",
                              "--trajectories", "0", "--no-plots", "--out", "ev")
    assert proc.returncode == 0, proc.stderr
    return tmp / "ev"


def _header_only(ev: Path) -> None:
    text = (ev / "episodes.csv").read_text()
    (ev / "episodes.csv").write_text(text.splitlines(keepends=True)[0])


def _cut(ev: Path) -> None:
    text = (ev / "episodes.csv").read_text()
    (ev / "episodes.csv").write_text("".join(text.splitlines(keepends=True)[:3]))  # header and 2 of 3 rows


def _written_twice(ev: Path) -> None:
    text = (ev / "episodes.csv").read_text()
    (ev / "episodes.csv").write_text(text + text)  # what two evaluations at once left before the lock


@pytest.mark.parametrize("damage,expected", [
    (lambda ev: (ev / "episodes.csv").unlink(), "ev/episodes.csv: not found (seeds 10000000..10000002), but "),
    (_header_only, "ev/episodes.csv: 0 episodes of seeds 10000000..10000002, but "),
    (_cut, "ev/episodes.csv: 2 episodes of seeds 10000000..10000002, but "),
    (_written_twice, "ev/episodes.csv: line 5 repeats the header: two processes wrote this file at once"),
    (lambda ev: (ev / "summary.json").write_text('{"episodes": 3, "first_se'), "ev/summary.json: not valid JSON"),
    (lambda ev: (ev / "summary.json").write_text("[3]"), "ev/summary.json: expected a JSON object, got list"),
    (lambda ev: (ev / "summary.json").write_text('{"episodes": 3}'), "ev/summary.json: no first_seed"),
    (lambda ev: (ev / "summary.json").write_text('{"episodes": "3", "first_seed": 0}'),
     "ev/summary.json: episodes '3' is not int"),
], ids=["deleted", "header-only", "cut", "written-twice", "corrupt-summary", "list-summary", "no-first-seed",
        "string-count"])
def test_compare_refuses_an_evaluation_whose_files_disagree(evaluation: Path, cli: Any, damage: Any,
                                                            expected: str) -> None:
    shutil.copytree(evaluation, cli.folder / "ev")
    damage(cli.folder / "ev")
    proc = cli.run("compare", "ev", "--out", "report")
    cli.assert_clean_error(proc, expected)
    if "episodes.csv" in expected and "header" not in expected:
        assert "summary.json counts 3" in proc.stderr
    assert not (cli.folder / "report").exists()  # nothing written for a refused comparison


@pytest.mark.parametrize("damage,expected", [
    (_written_twice, "ev/episodes.csv: line 5 repeats the header"),
    (lambda ev: (ev / "evaluation.json").write_text('{"policy": "id'), "ev/evaluation.json: not a JSON object"),
], ids=["written-twice", "corrupt-evaluation-json"])
def test_evaluating_into_a_damaged_folder_is_one_line_not_a_traceback(evaluation: Path, cli: Any, damage: Any,
                                                                      expected: str) -> None:
    shutil.copytree(evaluation, cli.folder / "ev")
    damage(cli.folder / "ev")
    before = cli.folder_state(cli.folder / "ev")
    proc = cli.run("evaluate", "--config", cli.SMOKE, "--policy", "idle", "--episodes", "3", "--out", "ev")
    cli.assert_clean_error(proc, expected)
    assert cli.folder_state(cli.folder / "ev") == before


# -- --resume checks the run's files against its checkpoint --------------------------------------------------
@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory: pytest.TempPathFactory, cli_class: type) -> Path:
    """A finished 4-episode smoke run (2 updates, a checkpoint at each)."""
    tmp = tmp_path_factory.mktemp("smoke_run")
    proc = cli_class(tmp).run("train", "--config", cli_class.SMOKE, "--out", "run",
                              *cli_class.settings("train.episodes=4", "train.checkpoint_every=1"))
    assert proc.returncode == 0, proc.stderr
    return tmp / "run"


def _keep_rows(path: Path, n: int) -> None:
    path.write_text("".join(path.read_text().splitlines(keepends=True)[:n + 1]))


@pytest.mark.parametrize("damage,warnings", [
    pytest.param(lambda run: (run / "episodes.csv").unlink(),
                 ["run/episodes.csv is missing; it held the 4 episodes that the checkpoint counts"],
                 id="deleted", marks=pytest.mark.slow),  # 8 s; the cut logs warn alike in the default tier
    pytest.param(lambda run: (_keep_rows(run / "episodes.csv", 1), _keep_rows(run / "updates.csv", 1)),
                 ["run/episodes.csv holds 1 of the 4 episodes that the checkpoint counts",
                  "run/updates.csv ends at update 1, but the checkpoint is at update 2 (a row every 1"], id="cut"),
])
def test_resume_warns_of_logs_that_lack_the_checkpoints_rows(smoke_run: Path, cli: Any, damage: Any,
                                                            warnings: list[str]) -> None:
    shutil.copytree(smoke_run, cli.folder / "run")
    damage(cli.folder / "run")
    proc = cli.run("train", "--config", cli.SMOKE, "--out", "run", "--resume",
                   *cli.settings("train.episodes=6", "train.checkpoint_every=1"))
    assert proc.returncode == 0, proc.stderr
    for warning in warnings:
        assert any(" WARNING " in line and warning in line for line in proc.stderr.splitlines()), proc.stderr
    assert read_checkpoint(cli.folder / "run" / "checkpoint.pt")["counters"]["episodes"] == 6


def _duplicate_episode(run: Path) -> None:
    lines = (run / "episodes.csv").read_text().splitlines(keepends=True)
    (run / "episodes.csv").write_text("".join(lines + lines[1:2]))  # two writers, one header: a row twice


@pytest.mark.parametrize("damage,expected", [
    (lambda run: (run / "config.yaml").write_text("sim: [1, 2\n"), "run/config.yaml: not valid YAML: line 2"),
    (lambda run: (run / "config.yaml").write_bytes(b"sim:\n  seed: \xff\n"),
     "run/config.yaml: not UTF-8 text (byte 0xff on line 2)"),
    (lambda run: (run / "config.yaml").write_text("- sim\n- train\n"),
     "run/config.yaml: not a mapping of config sections"),
    (lambda run: _written_twice_run(run), "run/episodes.csv: line 6 repeats the header"),
    (_duplicate_episode, "run/episodes.csv: rows 1 and 5 are both episode 1: two processes wrote this run"),
], ids=["not-yaml", "not-utf8", "not-a-mapping", "written-twice", "episode-twice"])
def test_resume_refuses_a_damaged_run_folder_in_one_line_and_leaves_it_unchanged(smoke_run: Path, cli: Any,
                                                                                 damage: Any, expected: str) -> None:
    shutil.copytree(smoke_run, cli.folder / "run")
    damage(cli.folder / "run")
    before = cli.folder_state(cli.folder / "run")
    proc = cli.run("train", "--config", cli.SMOKE, "--out", "run", "--resume", "--set", "train.checkpoint_every=1")
    cli.assert_clean_error(proc, expected)
    assert cli.folder_state(cli.folder / "run") == before


def _written_twice_run(run: Path) -> None:
    text = (run / "episodes.csv").read_text()
    (run / "episodes.csv").write_text(text + text)
