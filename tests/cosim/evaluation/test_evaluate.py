"""`cosim evaluate` / `cosim compare` on real SUMO, short: baselines on two nets, a tiny checkpoint, resume,
bad input, and the report's figures as non-empty PNGs."""

from __future__ import annotations

import csv
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from agents.checkpoint import CheckpointError, TrainedPolicy, act_agents, save_checkpoint
from agents.model import ActorCritic
from cosim.cli import main
from cosim.config import load_config
from cosim.environment.control import Action
from cosim.errors import ConfigError, CosimError, NetError
from cosim.evaluation.compare import compare
from cosim.evaluation.runner import Baseline, Job, evaluate, run_episodes
from cosim.evaluation.store import config_hash, summarize_evaluation
from cosim.files import read_csv
from sumo_net.build import run_netconvert

pytestmark = pytest.mark.sumo  # runs SUMO (libsumo or netconvert)

SHORT = ["sim.horizon=8"]
PNG = b"\x89PNG\r\n\x1a\n"


def _cfg(*extra: str):
    return load_config("configs/default.yaml", [*SHORT, *extra])


def _is_png(path: Path) -> bool:
    return path.is_file() and path.stat().st_size > 2000 and path.read_bytes()[:8] == PNG


@pytest.fixture(scope="module")
def idle_eval(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("eval") / "idle"
    evaluate(_cfg(), Baseline("idle"), out, episodes=3, seed=100, trajectories=1)
    return out


def test_evaluation_files_and_summary(idle_eval: Path) -> None:
    rows = read_csv(idle_eval / "episodes.csv")
    assert [int(r["seed"]) for r in rows] == [100, 101, 102]
    for key in ("length", "crashed", "crash_av", "crash_hv", "crash_merger", "merged", "merge_failed",
                "time_to_merge", "mean_distance", "av_distance",
                "hv_distance", "merger_distance", "av_speed", "guide_av", "guide_actions", "throughput_vph",
                "time_loss", "window_speed", "distance_check", "conflicts", "conflicts_ttc", "conflicts_drac",
                "conflicts_pet", "conflicts_av", "conflicts_merger", "min_ttc", "hard_brakes", "hard_brakes_hv",
                "hard_brakes_av", "hard_brakes_merger"):
        assert key in rows[0], key
    assert all(float(r["distance_check"]) < 0.01 for r in rows)  # our distance and SUMO's agree
    assert all(r["guide_av"].startswith("av_") for r in rows)
    summary = json.loads((idle_eval / "summary.json").read_text())
    assert summary["episodes"] == 3 and summary["policy"] == "idle"
    crash = summary["metrics"]["crash [%]"]
    assert crash["n"] == 3 and 0 <= crash["ci_low"] <= crash["mean"] <= crash["ci_high"] <= 100
    assert summary["metrics"]["throughput [veh/h]"]["mean"] > 0
    for label in ("conflicts with an AV [per episode]", "hard braking, merging vehicle [events per episode]"):
        assert summary["metrics"][label]["n"] == 3, label  # in every episode's row, with an interval
    assert (idle_eval / "sumo" / "episode_100" / "ssm.xml").is_file()
    assert (idle_eval / "trajectories" / "seed_100.npz").is_file()
    assert not (idle_eval / "trajectories" / "seed_101.npz").exists()
    for name in ("merger_distance.png", "timespace_seed_100.png", "topview_seed_100.png"):
        assert _is_png(idle_eval / "plots" / name), name


def test_summary_is_strict_json_with_null_where_a_figure_has_no_value(tmp_path: Path) -> None:
    def refuse(constant: str) -> None:
        raise ValueError(f"not JSON: {constant}")

    summary = evaluate(_cfg(), Baseline("idle"), tmp_path / "one", episodes=1, trajectories=0, plots=False)
    assert not math.isnan(summary["metrics"]["crash [%]"]["ci_low"])  # a rate has a Wilson interval at n = 1
    strict = json.loads((tmp_path / "one" / "summary.json").read_text(), parse_constant=refuse)
    assert strict["metrics"]["mean distance [m]"]["ci_low"] is None  # one episode: no t-interval
    compare([tmp_path / "one"], tmp_path / "report")
    json.loads((tmp_path / "report" / "summary.json").read_text(), parse_constant=refuse)


def test_resume_skips_done_episodes_and_drops_a_partial_row(idle_eval: Path, tmp_path: Path) -> None:
    out = tmp_path / "resumed"
    shutil.copytree(idle_eval, out)
    lines = (out / "episodes.csv").read_text().splitlines(keepends=True)
    (out / "episodes.csv").write_text("".join(lines[:3]) + lines[3][:25])  # interrupted mid-row of seed 102
    evaluate(_cfg(), Baseline("idle"), out, episodes=4, seed=100, trajectories=0, plots=False)
    rows = read_csv(out / "episodes.csv")
    assert [int(r["seed"]) for r in rows] == [100, 101, 102, 103]
    original = read_csv(idle_eval / "episodes.csv")
    assert rows[2]["mean_distance"] == original[2]["mean_distance"]  # re-run deterministically
    with pytest.raises(CosimError, match="other policy"):
        evaluate(_cfg(), Baseline("random"), out, episodes=1, seed=100, plots=False)


def test_resume_with_another_config_is_refused(idle_eval: Path, tmp_path: Path) -> None:
    out = tmp_path / "other"
    shutil.copytree(idle_eval, out)
    before = (out / "episodes.csv").read_text()
    with pytest.raises(ConfigError, match=f"{out}.*another config"):
        evaluate(_cfg("reward.phi=0.5"), Baseline("idle"), out, episodes=4, seed=100, plots=False)
    assert (out / "episodes.csv").read_text() == before  # nothing of the other config mixed in
    # A folder from before the hash was stored: its config.yaml is hashed instead.
    meta = json.loads((out / "evaluation.json").read_text())
    del meta["config_sha256"]
    (out / "evaluation.json").write_text(json.dumps(meta))
    with pytest.raises(ConfigError, match="another config"):
        evaluate(_cfg("reward.phi=0.5"), Baseline("idle"), out, episodes=4, seed=100, plots=False)
    evaluate(_cfg(), Baseline("idle"), out, episodes=3, seed=100, plots=False)  # the same config resumes


def test_a_folder_cloned_elsewhere_with_its_net_resumes(idle_eval: Path, tmp_path: Path) -> None:
    # A repository cloned to another path: the folder and the net (same content) are elsewhere, and the folder's
    # own records name the old paths. It resumes; another net's content is refused.
    out = tmp_path / "clone" / "idle"
    shutil.copytree(idle_eval, out)
    net_dir = shutil.copytree(Path("sumo_net/dilemma"), tmp_path / "clone" / "dilemma")
    evaluate(_cfg(f"net.file={net_dir / 'dilemma.net.xml'}"), Baseline("idle"), out, episodes=4, seed=100,
             trajectories=0, plots=False)
    assert [int(r["seed"]) for r in read_csv(out / "episodes.csv")] == [100, 101, 102, 103]
    with (net_dir / "dilemma.net.xml").open("a") as f:
        f.write("<!-- edited -->\n")
    with pytest.raises(CosimError, match="other net_sha256"):
        evaluate(_cfg(f"net.file={net_dir / 'dilemma.net.xml'}"), Baseline("idle"), out, episodes=5, seed=100,
                 trajectories=0, plots=False)


def test_a_trained_policys_folder_kept_as_results_keep_it_resumes_by_the_policys_content(tmp_path: Path) -> None:
    # Results kept in a repository hold summary.json, episodes.csv and config.yaml (no evaluation.json), and name the
    # checkpoint by the path it had where they were made. Cloned elsewhere with its policy, the folder resumes;
    # other weights at that path are refused, and so are episodes that nothing says the origin of.
    cfg = _cfg()
    shape = (cfg.observation.frames, len(cfg.observation.channels), cfg.observation.height_px,
             cfg.observation.width_px)
    (tmp_path / "made").mkdir()
    _tiny_checkpoint(tmp_path / "made" / "best.pt", shape)
    evaluate(cfg, TrainedPolicy(str(tmp_path / "made" / "best.pt")), tmp_path / "made" / "ev", episodes=2, seed=5,
             trajectories=0, plots=False)
    clone = tmp_path / "clone"
    clone.mkdir()
    shutil.copy(tmp_path / "made" / "best.pt", clone / "best.pt")
    (clone / "ev").mkdir()
    for name in ("summary.json", "episodes.csv", "config.yaml"):
        shutil.copy(tmp_path / "made" / "ev" / name, clone / "ev" / name)
    evaluate(cfg, TrainedPolicy(str(clone / "best.pt")), clone / "ev", episodes=3, seed=5, trajectories=0,
             plots=False)
    assert [int(r["seed"]) for r in read_csv(clone / "ev" / "episodes.csv")] == [5, 6, 7]
    _tiny_checkpoint(clone / "best.pt", shape)  # new random weights, the same counters
    with pytest.raises(CosimError, match="other model_sha256"):
        evaluate(cfg, TrainedPolicy(str(clone / "best.pt")), clone / "ev", episodes=4, seed=5, plots=False)
    for name in ("summary.json", "evaluation.json"):
        (clone / "ev" / name).unlink(missing_ok=True)
    with pytest.raises(CosimError, match="holds episodes .* but no evaluation.json or summary.json"):
        evaluate(cfg, TrainedPolicy(str(clone / "best.pt")), clone / "ev", episodes=4, seed=5, plots=False)


def test_a_folder_written_before_a_config_key_existed_resumes(idle_eval: Path, tmp_path: Path) -> None:
    # A key added to the config since (here demand.exit, taken out of the folder's config.yaml and its hash) takes
    # the default that keeps the old behaviour: the folder holds the same evaluation and resumes; one whose
    # config differs in a value does not.
    out = tmp_path / "older"
    shutil.copytree(idle_eval, out)
    saved = yaml.safe_load((out / "config.yaml").read_text())
    del saved["demand"]["exit"]
    (out / "config.yaml").write_text(yaml.safe_dump(saved, sort_keys=False))
    meta = json.loads((out / "evaluation.json").read_text())
    meta["config_sha256"] = config_hash(saved)
    (out / "evaluation.json").write_text(json.dumps(meta))
    evaluate(_cfg(), Baseline("idle"), out, episodes=4, seed=100, trajectories=0, plots=False)
    assert [int(r["seed"]) for r in read_csv(out / "episodes.csv")] == [100, 101, 102, 103]
    with pytest.raises(ConfigError, match="another config"):
        evaluate(_cfg("reward.phi=0.5"), Baseline("idle"), out, episodes=4, seed=100, plots=False)


def test_evaluate_and_compare_summarise_the_same_rows(idle_eval: Path, tmp_path: Path) -> None:
    out = tmp_path / "extra"
    shutil.copytree(idle_eval, out)
    # Rows of seeds this evaluation did not ask for (another --seed into the same folder, say).
    rows = read_csv(out / "episodes.csv")
    with (out / "episodes.csv").open("a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        for k in range(5):
            w.writerow({**rows[0], "seed": 500 + k, "crashed": "True", "mean_distance": "1.0"})
    summary = evaluate(_cfg(), Baseline("idle"), out, episodes=3, seed=100, trajectories=0, plots=False)
    picked, metrics = summarize_evaluation(out, 100, 3)
    same = json.dumps(summary["metrics"], sort_keys=True)  # as text: NaN == NaN
    assert [int(r["seed"]) for r in picked] == [100, 101, 102] and json.dumps(metrics, sort_keys=True) == same
    result = compare([out], tmp_path / "report")
    assert result["extra"]["episodes"] == summary["episodes"] == 3
    assert json.dumps(result["extra"]["metrics"], sort_keys=True) == same


@pytest.mark.parametrize("net", ["default", "two_lane"])
@pytest.mark.parametrize("policy", ["sumo", "random"])
def test_baselines_on_two_nets(net: str, policy: str, two_lane_net: Path, tmp_path: Path) -> None:
    extra = [f"net.file={two_lane_net}", "scenario.n_hvs=6"] if net == "two_lane" else []
    summary = evaluate(_cfg(*extra), Baseline(policy), tmp_path, episodes=2, seed=7, trajectories=0,
                       plots=False)
    assert summary["episodes"] == 2 and math.isfinite(summary["metrics"]["mean distance [m]"]["mean"])
    if policy == "sumo":
        assert read_csv(tmp_path / "episodes.csv")[0]["guide_actions"] == ""  # SUMO drives: no actions


def test_workers_give_the_same_rows(tmp_path: Path) -> None:
    job = Job(_cfg("sim.outputs=true", f"sim.output_dir={tmp_path}").to_dict(), Baseline("random"),
              str(tmp_path), frozenset())
    one = sorted(run_episodes(job, [1, 2], workers=1), key=lambda r: r["seed"])
    two = sorted(run_episodes(job, [1, 2], workers=2), key=lambda r: r["seed"])
    assert [r["mean_distance"] for r in one] == [r["mean_distance"] for r in two]


def _tiny_checkpoint(path: Path, obs_shape: tuple[int, ...], updates: int = 1, shared: bool = True,
                     train: dict | None = None, prefer: dict[int, float] | None = None) -> None:
    """`train`: the checkpoint's train section (none by default, as before it was saved); `prefer`: action -> a
    bias added to its logit, so that the greedy policy takes the most preferred."""
    nets = [ActorCritic(obs_shape, 5, feature_dim=8, head_hidden=8) for _ in range(1 if shared else 4)]
    for net in nets:
        with torch.no_grad():
            for action, bias in (prefer or {}).items():
                net.actor[-1].bias[action] += bias
    spec = {"agents": [f"av_{i}" for i in range(4)], "obs_shape": list(obs_shape), "obs_dtype": "float32",
            "n_actions": 5, "shared_policy": shared, "feature_dim": 8, "head_hidden": 8}
    save_checkpoint(path, {"spec": spec, "policy": {"nets": [n.state_dict() for n in nets]},
                           "counters": {"updates": updates}, "rng": {}, **({"train": train} if train else {})})


@pytest.mark.parametrize("masked", [True, False])
def test_a_policy_trained_with_action_masks_is_evaluated_with_the_envs(tmp_path: Path, masked: bool) -> None:
    """A network that prefers lane-right above all, then accelerate: the AVs drive in the right through lane, where
    lane-right is masked, so a run trained with masks evaluates with them and never takes it; one trained without
    always does (the env ignores it)."""
    cfg = _cfg()
    shape = (cfg.observation.frames, len(cfg.observation.channels), cfg.observation.height_px,
             cfg.observation.width_px)
    path = tmp_path / "checkpoint.pt"
    _tiny_checkpoint(path, shape, train={"action_mask": masked}, prefer={Action.LANE_RIGHT: 100.0,
                                                                        Action.ACCELERATE: 50.0})
    evaluate(cfg, TrainedPolicy(str(path)), tmp_path / "ev", episodes=1, seed=5, trajectories=0, plots=False)
    actions = read_csv(tmp_path / "ev" / "episodes.csv")[0]["guide_actions"].split()
    assert actions and (str(int(Action.LANE_RIGHT)) not in actions if masked else
                        set(actions) == {str(int(Action.LANE_RIGHT))})


def test_act_agents_batches_agents_sharing_a_network() -> None:
    shape = (2, 3, 8, 8)
    shared, own = ActorCritic(shape, 5, feature_dim=8, head_hidden=8), ActorCritic(shape, 5, feature_dim=8,
                                                                                  head_hidden=8)
    policies = {"av_0": shared, "av_1": shared, "av_2": own}
    calls = []
    for net in (shared, own):
        net.register_forward_hook(lambda m, args, out: calls.append(args[0].shape[0]))
    obs = {a: np.random.default_rng(i).random(shape, dtype=np.float32) for i, a in enumerate(policies)}
    actions = act_agents(policies, obs, greedy=True)
    assert sorted(calls) == [1, 2]  # one forward per network
    for a, net in policies.items():
        assert actions[a] == int(net(torch.from_numpy(obs[a][None]))[0].argmax())
    assert set(act_agents(policies, {"av_2": obs["av_2"]}, greedy=False)) == {"av_2"}  # live agents only


def test_checkpoint_policy_and_a_mismatched_one(tmp_path: Path) -> None:
    cfg = _cfg()
    shape = (cfg.observation.frames, len(cfg.observation.channels), cfg.observation.height_px,
             cfg.observation.width_px)
    good, bad = tmp_path / "good.pt", tmp_path / "bad.pt"
    _tiny_checkpoint(good, shape)
    _tiny_checkpoint(bad, (shape[0] + 1, *shape[1:]))
    summary = evaluate(cfg, TrainedPolicy(str(good), greedy=False), tmp_path / "ev", episodes=2, seed=5,
                       trajectories=0, plots=False)
    assert summary["episodes"] == 2 and summary["greedy"] is False
    actions = read_csv(tmp_path / "ev" / "episodes.csv")[0]["guide_actions"].split()
    assert actions and all(0 <= int(a) < 5 for a in actions)
    # The same checkpoint file trained further: its old evaluation is not resumed as if it were the new one's.
    _tiny_checkpoint(good, shape, updates=9)
    with pytest.raises(CosimError, match="other trained_updates"):
        evaluate(cfg, TrainedPolicy(str(good), greedy=False), tmp_path / "ev", episodes=4, seed=5,
                 trajectories=0, plots=False)
    with pytest.raises(CheckpointError, match="observations of shape"):
        evaluate(cfg, TrainedPolicy(str(bad)), tmp_path / "ev_bad", episodes=1, plots=False)
    assert not (tmp_path / "ev_bad" / "evaluation.json").exists()  # a failed start claims no folder


def test_a_trained_policy_under_demand_without_avs_runs_as_the_baselines_do(tmp_path: Path) -> None:
    cfg = _cfg()
    shape = (cfg.observation.frames, len(cfg.observation.channels), cfg.observation.height_px,
             cfg.observation.width_px)
    _tiny_checkpoint(tmp_path / "good.pt", shape)
    demand = load_config(cfg, {"demand.enabled": True, "demand.warmup": 30.0, "demand.window": 60.0,
                               "demand.av_penetration": 0.0})
    summary = evaluate(demand, TrainedPolicy(str(tmp_path / "good.pt")), tmp_path / "ev", episodes=1, plots=False)
    assert summary["episodes"] == 1 and summary["metrics"]["throughput, total [veh/h]"]["mean"] > 0


def test_bad_input_is_a_clear_error(tmp_path: Path, two_lane_net: Path, caplog) -> None:
    run = tmp_path / "run"
    run.mkdir()
    (run / "config.yaml").write_text("sim:\n  horizon: 5\n")
    assert main(["evaluate", "--run", str(run), "--episodes", "1"]) == 2
    assert "checkpoint" in caplog.text and "not found" in caplog.text
    assert main(["evaluate", "--run", str(tmp_path / "nothing")]) == 2
    for flag, value in (("--episodes", "0"), ("--episodes", "-2"), ("--trajectories", "-1"), ("--workers", "0")):
        caplog.clear()
        assert main(["evaluate", "--policy", "idle", flag, value, "--out", str(tmp_path / "ev0")]) == 2
        assert f"{flag}: must be >=" in caplog.text and f"got {value}" in caplog.text
        assert not (tmp_path / "ev0").exists()
    with pytest.raises(ConfigError, match="episodes: must be >= 1"):
        evaluate(_cfg(), Baseline("idle"), tmp_path / "ev0", episodes=0, plots=False)
    with pytest.raises(ConfigError, match="evaluate.episode"):
        load_config(_cfg(), {"evaluate.episode": 3})
    # A net without a merge: the 2-lane net with its ramp taken out.
    for name in ("merge.nod.xml", "merge.edg.xml", "merge.con.xml"):
        shutil.copy(two_lane_net.with_name(name), tmp_path / name)
    for name, key in (("merge.edg.xml", 'id="ramp"'), ("merge.con.xml", 'from="ramp"')):
        f = tmp_path / name
        f.write_text("\n".join(line for line in f.read_text().splitlines() if key not in line))
    straight = run_netconvert(tmp_path, "merge")
    with pytest.raises(NetError, match="cannot infer"):
        evaluate(_cfg(f"net.file={straight}"), Baseline("idle"), tmp_path / "ev", episodes=1, plots=False)


def test_cli_evaluate_and_compare_report(idle_eval: Path, tmp_path: Path, capsys) -> None:
    sumo_out = tmp_path / "sumo"
    assert main(["evaluate", "--policy", "sumo", "--episodes", "2", "--seed", "100", "--trajectories", "1",
                 "--set", "sim.horizon=8", "--out", str(sumo_out)]) == 0
    assert "crash [%]" in capsys.readouterr().out
    # A run folder with the trainer's log and its evaluation in eval/.
    run = tmp_path / "run_a"
    shutil.copytree(idle_eval, run / "eval")
    with (run / "episodes.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["episode", "return_mean", "crashed", "merged", "mean_distance"])
        for i in range(50):
            w.writerow([i, np.sin(i / 5), i % 2, 1, 100 + i])
    report = tmp_path / "report"
    assert main(["compare", str(run), str(sumo_out), "--out", str(report), "--labels", "egoistic", "human"]) == 0
    text = (report / "report.md").read_text()
    assert "| crash [%]" in text and "egoistic (n=3)" in text and "human (n=2)" in text
    for name in ("bars.png", "merger_distance.png", "training_curves.png", "egoistic/timespace_seed_100.png",
                 "human/topview_seed_100.png"):
        assert _is_png(report / name), name
        assert f"({name})" in text
    with pytest.raises(CosimError, match="no evaluation"):
        compare([tmp_path / "nothing"], report)


class _FailsAtItsFirstAct(Baseline):
    """A baseline whose first decision raises a config error, as a policy that does not fit the net does."""

    def load(self, env, worker):  # noqa: ANN001, ANN201 - the Policy protocol's signature
        def act(obs):  # noqa: ANN001, ANN202
            raise ConfigError("scenario.merger_pos: must be within the ramp edge 'ramp' (0 to 119.3 m)")

        return lambda seed: act


@pytest.mark.parametrize("existing", [False, True])
def test_a_failed_evaluation_leaves_nothing_that_blocks_its_rerun(tmp_path: Path, existing: bool) -> None:
    out = tmp_path / "eval"
    if existing:  # a folder of the user's, with a file of theirs
        out.mkdir()
        (out / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="scenario.merger_pos"):
        evaluate(_cfg("sim.horizon=2"), _FailsAtItsFirstAct("scripted"), out, episodes=2, seed=100, trajectories=1)
    # As found: no evaluation.json, config.yaml, episodes.csv or SUMO outputs of the failed attempt.
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"] if existing else not out.exists()
    # The corrected rerun (another policy, another config) into the same folder goes through.
    summary = evaluate(_cfg(), Baseline("idle"), out, episodes=2, seed=100, trajectories=0, plots=False)
    assert summary["episodes"] == 2 and summary["policy"] == "idle"


def test_an_evaluation_records_what_it_ran_on_and_compare_warns_across_nets(
        two_lane_net: Path, tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    main(["evaluate", "--policy", "idle", "--episodes", "2", "--set", "sim.horizon=8", "--no-plots", "--out",
          str(tmp_path / "dilemma")])
    assert main(["evaluate", "--policy", "idle", "--episodes", "2", "--set", "sim.horizon=8", "--no-plots",
                 "--net", str(two_lane_net), "--out", str(tmp_path / "two_lane")]) == 0
    summaries = {n: json.loads((tmp_path / n / "summary.json").read_text()) for n in ("dilemma", "two_lane")}
    two = summaries["two_lane"]["setting"]
    assert two["net"]["file"] == str(two_lane_net) and len(two["net"]["sha256"]) == 64
    assert two["overrides"] == ["sim.horizon=8", f"net.file={two_lane_net}", "net.description=null"]
    assert two["flow_window_s"] == 8.0 and two["detector"]["edge"] == "hw_out"
    assert summaries["two_lane"]["net_sha256"] != summaries["dilemma"]["net_sha256"]
    report = (tmp_path / "two_lane" / "report.md").read_text()
    for needle in ("## Setting (the same for every run)", "highway: hw_in (2 lanes",
                   "acceleration lane(s) [0] of 'hw_merge'", "overrides: `--set sim.horizon=8`",
                   "flow window: the first 8 s of each episode", "| merge success [%] |"):
        assert needle in report, needle
    caplog.set_level("WARNING")
    compare([tmp_path / "dilemma", tmp_path / "two_lane"], tmp_path / "report")
    assert "different net file content (net_sha256)" in caplog.text
    text = (tmp_path / "report" / "report.md").read_text()
    assert "## Setting of dilemma" in text and "## Setting of two_lane" in text


def test_the_terminal_table_and_the_report_call_a_trained_run_alike(tmp_path: Path, capsys) -> None:
    cfg = _cfg()
    run = tmp_path / "smoke_run"
    run.mkdir()
    (run / "config.yaml").write_text(yaml.safe_dump(cfg.to_dict(), sort_keys=False))
    _tiny_checkpoint(run / "checkpoint.pt", (cfg.observation.frames, len(cfg.observation.channels),
                                             cfg.observation.height_px, cfg.observation.width_px))
    assert main(["evaluate", "--run", str(run), "--episodes", "1", "--no-plots", "--out", str(tmp_path / "ev")]) == 0
    header = capsys.readouterr().out.splitlines()[0]
    report = (tmp_path / "ev" / "report.md").read_text()
    assert "smoke_run (n=1)" in header and "| smoke_run (n=1) |" in report and "Runs: **smoke_run**" in report
    # One episode: the t-intervals are missing, and the report says so (the rates keep their Wilson interval).
    assert "With a single episode there is no Student t interval" in report


def test_a_demand_report_states_the_demand_not_the_episode_scenario(tmp_path: Path) -> None:
    out = tmp_path / "demand"
    assert main(["evaluate", "--policy", "sumo", "--config", "configs/demand.yaml", "--episodes", "1", "--no-plots",
                 "--set", "demand.warmup=30", "--set", "demand.window=60", "--out", str(out)]) == 0
    setting = (out / "report.md").read_text().split("## Setting")[1]
    for needle in ("- demand: mainline 1440 veh/h per lane on 2 lane(s) (60% of a highway lane's 2400 pc/h), ramp "
                   "840 veh/h (40% of its 2100 pc/h)", "- AVs: 10% of the mainline vehicles",
                   "- times: warm-up 30 s (not measured), then a 60 s measurement window",
                   "- runs: one per seed, seed 10000000", "- drivers: AVs: top speed",
                   "- overrides: `--set demand.warmup=30` `--set demand.window=60`"):
        assert needle in setting, needle
    # The episode scenario's lines mean nothing here.
    for needle in ("flow window", "each episode", "a stream of HVs", "the merging vehicle starts"):
        assert needle not in setting, needle
    # One run: no interval at all, and the report says so.
    assert "With a single run there is no interval" in (out / "report.md").read_text()


def test_cli_evaluate_videos_beside_the_time_space_diagrams(tmp_path: Path, caplog) -> None:
    out = tmp_path / "ev"
    assert main(["evaluate", "--policy", "courteous", "--episodes", "2", "--seed", "100", "--trajectories", "1",
                 "--videos", "1", "--set", "sim.horizon=3", "--out", str(out)]) == 0
    plots_dir = out / "plots"
    assert sorted(p.name for p in plots_dir.glob("video_seed_*")) == ["video_seed_100.mp4"]
    assert (plots_dir / "timespace_seed_100.png").is_file()
    report = (out / "report.md").read_text()
    assert "[video_seed_100 (MP4)](plots/video_seed_100.mp4)" in report
    assert "![timespace_seed_100](plots/timespace_seed_100.png)" in report and "| crash [%]" in report
    # `cosim compare` links the evaluation's videos where they are.
    assert main(["compare", str(out), "--labels", "courteous", "--out", str(tmp_path / "cmp")]) == 0
    assert "[video_seed_100 (MP4)](../ev/plots/video_seed_100.mp4)" in (tmp_path / "cmp" / "report.md").read_text()
    caplog.clear()
    bad = ["evaluate", "--policy", "idle", "--episodes", "1", "--videos", "-1", "--out", str(tmp_path / "x")]
    assert main(bad) == 2
    assert caplog.messages == ["--videos: must be >= 0, got -1"]


def test_evaluate_under_demand_writes_the_flow_metrics_figures_and_level_of_service(tmp_path: Path) -> None:
    out = tmp_path / "demand"
    assert main(["evaluate", "--policy", "courteous", "--config", "configs/demand.yaml", "--episodes", "2",
                 "--set", "demand.warmup=30", "--set", "demand.window=60", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["episodes"] == 2 and summary["demand"]["level_of_service"] in "ABCDEF"
    assert summary["demand"]["mainline_vph"] == pytest.approx(0.6 * 2400)  # a share of the HCM capacity
    for label in ("throughput, total [veh/h]", "ramp queue, max [veh]", "delay per vehicle [s]",
                  "total time spent [veh h]", "distance per vehicle [m]", "density, merge influence area [veh/km/ln]",
                  "merge success, per merging vehicle [%]"):
        assert summary["metrics"][label]["n"] == 2, label
    for name in ("speed_heatmap.png", "merge_time_space.png", "flow_density.png"):
        assert _is_png(out / "plots" / name), name
    report = (out / "report.md").read_text()
    assert "level of service" in report and "flow_density.png" in report
    # Its outputs stay small: SUMO's files and the record of a 90 s run.
    assert sum(p.stat().st_size for p in (out / "sumo").rglob("*") if p.is_file()) < 3_000_000


@pytest.mark.parametrize("shared", [True, False])
def test_a_shared_network_drives_every_av_under_demand_a_per_av_one_is_refused(tmp_path: Path, shared: bool) -> None:
    cfg = _cfg()
    shape = (cfg.observation.frames, len(cfg.observation.channels), cfg.observation.height_px,
             cfg.observation.width_px)
    path = tmp_path / "checkpoint.pt"
    _tiny_checkpoint(path, shape, shared=shared)
    demand = load_config("configs/demand.yaml", ["demand.interval=10", "demand.warmup=10", "demand.window=20"])
    if shared:
        summary = evaluate(demand, TrainedPolicy(str(path)), tmp_path / "eval", episodes=1, plots=False)
        assert summary["episodes"] == 1
    else:
        with pytest.raises(CheckpointError, match=r"one network per AV .* train with a shared network"):
            evaluate(demand, TrainedPolicy(str(path)), tmp_path / "eval", episodes=1, plots=False)
