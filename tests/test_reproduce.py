"""scripts/reproduce.py: a recipe's runs train once, in the order their fine-tunes need, and a second call goes on
from where the first stopped (a run short of its episodes resumes, a finished one is left as it is)."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

from agents.checkpoint import read_checkpoint

ROOT = Path(__file__).resolve().parents[1]
spec = importlib.util.spec_from_file_location("reproduce", ROOT / "scripts" / "reproduce.py")
reproduce = sys.modules["reproduce"] = importlib.util.module_from_spec(spec)  # dataclasses look their module up
spec.loader.exec_module(reproduce)


def test_every_recipe_lists_its_commands_and_a_fine_tune_comes_after_what_it_starts_from() -> None:
    done = subprocess.run([sys.executable, "scripts/reproduce.py", "--list"], capture_output=True, text=True,
                          cwd=ROOT, check=True)
    for name in reproduce.RECIPES:
        assert f"{name}: " in done.stdout
    order = [r.name for r in reproduce._needed(reproduce.RECIPES["mixed_merger"])]
    assert len(order) == 12
    for seed in reproduce.SEEDS:
        assert order.index(f"hw1_pi4_s{seed}") < order.index(f"mix_pi4_s{seed}")
    longer = {r.name: r for r in reproduce._needed(reproduce.RECIPES["mixed_15k"])}
    assert longer["mix15k_phi0_s17"].episodes == 15000 and longer["mix15k_phi0_s17"].init_from.name == "hw1_phi0_s17"
    assert "--impatient-episodes" in reproduce.RECIPES["mixed_15k"].evaluation(Path("r"), Path("o"))
    full = reproduce.RECIPES["mixed_30k"]
    assert [r.episodes for r in full.runs] == [30000] * 6 and full.runs[0].name == "mixfull_phi0_s15"
    assert all(r.init_from.name.startswith("hw1_") for r in full.runs)
    # the shipped pair's other results play the same two runs mixed_30k trains, not two more
    for name in ("transfer_mixed", "demand_mixed"):
        assert reproduce.RECIPES[name].runs == full.runs[::3]


def test_a_bad_parallel_is_one_line() -> None:
    done = subprocess.run([sys.executable, "scripts/reproduce.py", "transfer", "--parallel", "0"], cwd=ROOT,
                          capture_output=True, text=True)
    assert done.returncode == 2 and "--parallel must be >= 1, got 0" in done.stderr and "Traceback" not in done.stderr


@pytest.mark.sumo
@pytest.mark.slow  # two short trainings, over 30 s: CI runs it with the long tests
def test_runs_train_once_and_a_longer_one_resumes(tmp_path: Path) -> None:
    short = reproduce.Run("smoke", ("train.seed=3",), 4, "configs/smoke.yaml")
    assert reproduce._state(short, tmp_path) == "new"
    reproduce._train([short], set(), tmp_path, parallel=1)
    assert reproduce._state(short, tmp_path) == "done"
    longer = reproduce.Run("smoke", ("train.seed=3",), 8, "configs/smoke.yaml")
    assert reproduce._state(longer, tmp_path) == "partial"
    assert "--resume" in longer.argv(tmp_path, resume=True)
    reproduce._train([longer], {"smoke"}, tmp_path, parallel=1)
    assert int(read_checkpoint(tmp_path / "smoke" / "checkpoint.pt")["counters"]["episodes"]) >= 8
    log = (tmp_path / "logs" / "smoke.log").read_text()
    assert log.count("trained") >= 2, log[-2000:]


def test_every_recipe_names_a_committed_report() -> None:
    for name, recipe in reproduce.RECIPES.items():
        assert (ROOT / recipe.report).is_file(), f"{name}: {recipe.report}"
