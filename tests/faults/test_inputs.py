"""Bad config and command-line input through the `cosim` command, as a user meets it: one line naming the input
and what is allowed, exit 2, before anything runs (no SUMO, no training), and nothing written: the output folder
not created, every file in the working folder as it was, nothing left in the temporary folder."""

from __future__ import annotations

import resource
import subprocess
from pathlib import Path
from typing import Any

import pytest

from cosim.config import SEED_MAX

SMOKE = str(Path(__file__).resolve().parents[2] / "configs" / "smoke.yaml")
SEEDS = f"expected an integer in [0, {SEED_MAX}] (SUMO's --seed is a 32-bit signed integer), got"

# Config files a case may name: written into the working folder before the command runs.
FILES = {
    "latin1.yaml": f"base: {SMOKE}\nsim:\n  seed: 1  # caf\xe9\n".encode("latin-1"),
    "twice.yaml": f"base: {SMOKE}\nsim:\n  seed: 1\nscenario:\n  n_hvs: 2\nsim:\n  horizon: 5\n".encode(),
    "twice_in_sim.yaml": f"base: {SMOKE}\nsim:\n  seed: 1\n  horizon: 5\n  seed: 2\n".encode(),
    "unclosed.yaml": f"base: {SMOKE}\nsim: [1, 2\n".encode(),
    # A training run folder whose config.yaml someone edited by hand: `evaluate --run` reads it.
    "run/config.yaml": f"base: {SMOKE}\ntrain:\n  seed: 1\ntrain:\n  seed: 2\n".encode(),
}


def _run_scenario(*args: str) -> list[str]:
    return ["run-scenario", "--config", SMOKE, "--episodes", "1", *args]


def _evaluate(*args: str) -> list[str]:
    return ["evaluate", "--config", SMOKE, "--policy", "idle", "--out", "out", *args]


def _train(*args: str) -> list[str]:
    return ["train", "--out", "out", *args]


CASES = {
    # Seeds: one range everywhere, checked before SUMO starts or anything is written.
    "run-scenario --seed": (_run_scenario("--seed", "-1", "--save-routes", "out"), f"--seed: {SEEDS} -1"),
    "run-scenario --seed and --episodes": (
        _run_scenario("--seed", str(SEED_MAX), "--episodes", "2", "--save-routes", "out"),
        f"--seed: expected an integer in [0, {SEED_MAX - 1}], so that the seeds of all 2 episodes fit"),
    "sim.seed negative": (_run_scenario("--set", "sim.seed=-3"), f"--set sim.seed=-3: {SEEDS} -3"),
    "sim.seed above 32 bits": (_run_scenario("--set", "sim.seed=3000000000"),
                               f"--set sim.seed=3000000000: {SEEDS} 3000000000"),
    "evaluate --seed": (_evaluate("--seed", "-5"),
                        "--seed: expected an integer in [0, 2147483548], so that the seeds of all 100"),
    "evaluate --seed and --episodes": (_evaluate("--seed", str(SEED_MAX - 5), "--episodes", "8"),
                                       "so that the seeds of all 8 episodes fit"),
    "evaluate.seed": (_evaluate("--set", f"evaluate.seed={SEED_MAX}"),
                      f"--set evaluate.seed={SEED_MAX}: expected an integer in [0, 2147483548]"),
    "train.seed": (_train("--config", SMOKE, "--set", "train.seed=-1"), f"--set train.seed=-1: {SEEDS} -1"),
    "sweep --seeds": (["sweep", "--config", SMOKE, "--phi", "0", "--seeds", "0", "-1", "--budget-min", "1",
                       "--out", "out"], f"--seeds: {SEEDS} -1"),
    # YAML that cannot be read: the file or the key, and where.
    "--set unparsable": (_train("--config", SMOKE, "--set", "reward.phi=[1,2"),
                         "override reward.phi: '[1,2' is not a YAML value: column 5: expected ',' or ']'"),
    "not UTF-8": (_train("--config", "latin1.yaml"), "config file latin1.yaml: not UTF-8 text (byte 0xe9 on line 3)"),
    "YAML syntax": (_train("--config", "unclosed.yaml"),
                    "config file unclosed.yaml: not valid YAML: line 3, column 1: expected"),
    "section twice": (_train("--config", "twice.yaml"),
                      "twice.yaml: not valid YAML: line 6, column 1: key sim given twice (first on line 2)"),
    "key twice in a section": (_train("--config", "twice_in_sim.yaml"),
                               "line 5, column 3: key sim.seed given twice (first on line 3)"),
    "run's config.yaml": (["evaluate", "--run", "run", "--policy", "idle", "--episodes", "1"],
                          "run/config.yaml: not valid YAML: line 4, column 1: key train given twice"),
    # Values that would fail deep inside (numpy's allocation) or run something else than asked.
    "observation size": (
        _train("--config", SMOKE, *["--set", "observation.frames=100000", "--set", "observation.height_px=4096",
                                    "--set", "observation.width_px=4096"]),
        "observation: frames x channels x height_px x width_px = 100000 x 4 x 4096 x 4096 = 6,710,886,400,000 "
        "values per agent, more than 16,777,216"),
    "step_length": (_run_scenario("--set", "sim.step_length=5", "--set", "sim.decision_period=5",
                                  "--set", "sim.horizon=1"), "--set sim.step_length=5: must be <= 1, got 5"),
    "horizon below a decision": (_run_scenario("--set", "sim.decision_period=5", "--set", "sim.horizon=1"),
                                 "--set sim.horizon=1: must be at least decision_period (5 s), got 1 s"),
    "horizon not whole decisions": (_run_scenario("--set", "sim.horizon=10.5"),
                                    "--set sim.horizon=10.5: must be a whole number of decision periods"),
    # Sizes that multiply memory: a batch of 1e8 decision steps, a million worker processes (each its own SUMO).
    "batch beyond memory": (_train("--config", SMOKE, "--set", "sim.horizon=100000000"),
                            "one update's batch (100,000,000 decision steps x 2 workers x 2 AVs x 81,920 observation "
                            "values): 30,517.6 GiB + 2 worker processes: 0.3 GiB; "),
    "train workers beyond memory": (_train("--config", SMOKE, "--workers", "1000000"),
                                    "+ 1000000 worker processes: 156,250.0 GiB; "),
    "evaluate workers beyond memory": (_evaluate("--workers", "1000000", "--episodes", "1000000"),
                                       "1000000 worker processes: 156,250.0 GiB; 156,250.0 GiB in all, more than this "
                                       "machine's"),
}
DEMAND = str(Path(__file__).resolve().parents[2] / "configs" / "demand.yaml")
SHORT_DEMAND = ("--set", "demand.warmup=30", "--set", "demand.window=60")
NEEDS_SUMO = {
    # More AVs than the demand releases: each would be an agent with its observation slot (22 GB, then killed).
    "demand.av_count": (["evaluate", "--config", DEMAND, *SHORT_DEMAND, "--set", "demand.av_count=100000", "--policy",
                         "courteous", "--episodes", "1", "--no-plots", "--out", "out"],
                        "demand.av_count: 100000 AVs, but the mainline demand (2880 veh/h on 2 lane(s)) releases about "
                        "72 vehicles over warmup + window (90 s), at most 124"),
    "demand's slots": (["evaluate", "--config", DEMAND, "--set", "demand.av_count=400", "--set",
                        "demand.max_avs_present=400", "--set", "observation.preset=paper", "--policy", "courteous",
                        "--episodes", "1", "--no-plots", "--out", "out"],
                       "demand.max_avs_present: 400 observation slots of 1,310,720 values each exceed the bound of "
                       "268,435,456 values (256 MiB as uint8; a worker keeps two stacks per slot): at most 204 slots"),
    # This one loads the net before it can know the seeds of every episode.
    "sim.seed and episodes": (_run_scenario("--set", f"sim.seed={SEED_MAX}", "--episodes", "2"),
                              "sim.seed: expected an integer in [0, 2147483646], so that the seeds of all 2"),
    # SUMO refuses an option: its own error line names it; ours must not blame the net.
    "sim.sumo_args": (_run_scenario("--set", "sim.sumo_args=[--no-such-option, '1']"),
                      "SUMO failed to start: Could not parse commandline options (SUMO's own error above names the "
                      "cause; its options: -n "),
}


@pytest.mark.parametrize("args,expected", [
    *(pytest.param(*case, id=name) for name, case in CASES.items()),
    *(pytest.param(*case, id=name, marks=pytest.mark.sumo) for name, case in NEEDS_SUMO.items()),
])
def test_bad_input_is_one_line_before_anything_is_written(cli: Any, tmp_path: Path, args: list[str],
                                                          expected: str) -> None:
    for name, data in FILES.items():
        (tmp_path / name).parent.mkdir(exist_ok=True)
        (tmp_path / name).write_bytes(data)
    before = _state(cli, tmp_path)
    cli.assert_clean_error(cli.run(*args, timeout=120), expected)
    assert not (tmp_path / "out").exists() and not (tmp_path / "run" / "eval").exists()
    assert _state(cli, tmp_path) == before
    assert cli.no_leftovers()


def _state(cli: Any, folder: Path) -> dict[str, str]:
    # The command's TMPDIR is the Cli's to check (torch may keep its caches there).
    return {k: v for k, v in cli.folder_state(folder).items() if not k.startswith("tmpdir/")}


@pytest.mark.sumo
def test_unbounded_avs_under_demand_end_in_one_line_under_a_memory_limit(cli: Any) -> None:
    """Before the bound, `av_count=20000` under a memory limit ended in numpy's out-of-memory traceback (and without
    one the process grew until the kernel killed it); the limit is this test's, never the machine's."""
    limit = 4 * 2**30

    def limited() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    proc = subprocess.run(cli.cmd("evaluate", "--config", DEMAND, *SHORT_DEMAND, "--set", "demand.av_count=20000",
                                  "--policy", "courteous", "--episodes", "1", "--no-plots", "--out", "out"),
                          cwd=cli.folder, capture_output=True, text=True, timeout=120, env=cli.env(),
                          preexec_fn=limited)
    cli.assert_clean_error(proc, "demand.av_count: 20000 AVs")
