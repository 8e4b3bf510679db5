"""Rollout, baselines and evaluation, with the real simulator and real worker processes."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gsmn.config import preset
from gsmn.evaluation import evaluate, make_policy, merge_results, parse_env_ids, results_dict, table_row
from gsmn.task.baselines import (
    AverageAction,
    AvgForwardPolicy,
    ExpertPolicy,
    RandomLandmarkPolicy,
    fit_avg_forward,
)
from gsmn.task.instructions import goal_position
from gsmn.task.metrics import summarize
from gsmn.task.rollout import EpisodeRecord, rollout, task_for_env
from gsmn.world.env import Env

pytestmark = pytest.mark.unit

TINY = preset("tiny")


def test_task_for_env_is_deterministic_and_its_path_ends_at_the_goal():
    a, b = task_for_env(75, TINY), task_for_env(75, TINY)
    assert a.instruction == b.instruction and np.array_equal(a.path, b.path)
    assert np.linalg.norm(a.path[-1] - a.instruction.goal) < TINY.expert.target_tolerance + 1e-6
    assert np.allclose(a.path[0], a.world.start_position)


def test_rollout_record_matches_what_was_flown():
    task = task_for_env(71, TINY)
    seen = []
    with Env(TINY) as env:
        record = rollout(env, ExpertPolicy(TINY), task, horizon=TINY.task.horizon,
                         on_step=lambda obs, action: seen.append((obs.step, obs.image.shape, action.stop)))
    assert record.stopped and seen[-1][2] and not any(stop for *_, stop in seen[:-1])
    assert [s for s, *_ in seen] == list(range(record.steps + 1))
    assert all(shape == (144, 256, 3) for _, shape, _ in seen)
    assert len(record.trajectory) == len(record.actions) == record.steps + 1
    assert (record.final_x, record.final_y) == record.trajectory[-1][:2]
    assert record.goal_distance == pytest.approx(math.dist((record.final_x, record.final_y),
                                                           (record.goal_x, record.goal_y)))
    assert record.success and record.goal_distance < 1.5
    assert EpisodeRecord.from_dict(json.loads(json.dumps(record.to_dict()))) == record


def test_horizon_ends_an_episode_that_never_stops():
    task = task_for_env(72, TINY)
    average = AverageAction(forward_velocity=0.5, yaw_rate=0.3, steps=1000, episodes=1)
    with Env(TINY, render=False) as env:
        record = rollout(env, AvgForwardPolicy(average), task, horizon=7)
    assert not record.stopped and record.steps == 7 and len(record.trajectory) == 8


@pytest.mark.slow
def test_random_landmark_goes_to_the_instructed_side_of_some_landmark():
    finals = {}
    for env_id in (70, 73, 76):
        task = task_for_env(env_id, TINY)
        with Env(TINY, render=False) as env:
            r1 = rollout(env, RandomLandmarkPolicy(TINY), task, TINY.task.horizon)
            r2 = rollout(env, RandomLandmarkPolicy(TINY), task, TINY.task.horizon)
        assert (r1.final_x, r1.final_y) == (r2.final_x, r2.final_y), "seeded per environment"
        targets = [goal_position(task.world, i, task.instruction.side) for i in range(len(task.world.landmarks))]
        nearest = min(math.dist((r1.final_x, r1.final_y), t) for t in targets)
        assert nearest < 1.5
        finals[env_id] = (r1.final_x, r1.final_y)
    assert len(set(finals.values())) == 3


def test_avg_forward_fits_saves_and_loads(tmp_path):
    records = evaluate("oracle", [70, 71, 72], TINY)
    average = fit_avg_forward(records)
    assert 0 < average.forward_velocity <= TINY.drone.max_forward_velocity
    assert average.steps == round(np.mean([r.steps for r in records])) and average.episodes == 3
    average.save(tmp_path / "avg.json")
    assert AverageAction.load(tmp_path / "avg.json") == average
    policy = make_policy("avg-forward", TINY, tmp_path / "avg.json")
    with Env(TINY, render=False) as env:
        record = rollout(env, policy, task_for_env(73, TINY), TINY.task.horizon)
    assert record.stopped and record.steps == average.steps
    with pytest.raises(FileNotFoundError, match="fit-avg-forward"):
        make_policy("avg-forward", TINY, tmp_path / "missing.json")


@pytest.mark.slow
def test_parallel_workers_give_the_same_records_as_one_process():
    ids = [70, 71, 72, 73]
    one = evaluate("random-point", ids, TINY, workers=1)
    two = evaluate("random-point", ids, TINY, workers=2)
    assert [r.env_id for r in two] == ids
    assert one == two


def test_parse_env_ids_and_unknown_systems():
    assert parse_env_ids("3:6") == [3, 4, 5]
    assert parse_env_ids("3,17,42") == [3, 17, 42]
    for bad in ("a:b", "", "-1,2", "5:5"):
        with pytest.raises(ValueError, match="env-ids"):
            parse_env_ids(bad)
    with pytest.raises(ValueError, match="unknown system 'gsmn-nope'"):
        make_policy("gsmn-nope", TINY)


@pytest.mark.slow
def test_an_evaluation_run_in_pieces_merges_into_the_whole(tmp_path):
    ids = [70, 71, 72, 73, 74]
    whole = results_dict("random-point", None, evaluate("random-point", ids, TINY), TINY, 1.0, 1)
    first = results_dict("random-point", None, evaluate("random-point", ids[:2], TINY), TINY, 0.4, 1)
    rest = results_dict("random-point", None, evaluate("random-point", ids[2:], TINY), TINY, 0.6, 1)
    merged = merge_results([first, rest])
    assert merged["env_ids"] == ids and merged["episodes"] == whole["episodes"]
    assert merged["summary"] == whole["summary"] and merged["seconds"] == 1.0
    with pytest.raises(ValueError, match="evaluated twice"):
        merge_results([first, first])
    with pytest.raises(ValueError, match="different systems"):
        merge_results([first, {**rest, "system": "oracle"}])
    # the same weights under two paths merge; different weights do not
    a, b, c = (tmp_path / n for n in "abc")
    for folder, weights in ((a, b"w1"), (b, b"w1"), (c, b"w2")):
        folder.mkdir()
        (folder / "weights.safetensors").write_bytes(weights)
        (folder / "meta.json").write_text(json.dumps({"saved": str(folder)}))
    assert merge_results([{**first, "checkpoint": str(a)}, {**rest, "checkpoint": str(b)}])["checkpoint"] == str(a)
    (a / "optimizer.safetensors").write_bytes(b"adam state")  # training state beside the weights: the same system
    assert merge_results([{**first, "checkpoint": str(a)}, {**rest, "checkpoint": str(b)}])["checkpoint"] == str(a)
    with pytest.raises(ValueError, match="different checkpoints"):
        merge_results([{**first, "checkpoint": str(a)}, {**rest, "checkpoint": str(c)}])


def test_table_row_shows_pruned_figures_in_brackets():
    records = evaluate("oracle", [70, 71], TINY)
    row = table_row("oracle", summarize(records))
    assert row.startswith("oracle") and row.count("(") == 4


@pytest.mark.slow
def test_cli_eval_writes_records_and_summary(tmp_path):
    out = tmp_path / "eval.json"
    run = subprocess.run([sys.executable, "-m", "gsmn.cli", "eval", "--system", "random-landmark", "--env-ids",
                          "70,71,72", "--json", str(out), "--preset", "tiny"], capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    assert "random-landmark" in run.stdout and "success %" in run.stdout
    d = json.loads(out.read_text())
    assert d["system"] == "random-landmark" and d["env_ids"] == [70, 71, 72]
    assert set(d["summary"]) >= {"success", "landmark_success", "mean_distance", "median_distance", "pruned"}
    assert len(d["episodes"]) == 3 and d["episodes"][0]["instruction"].startswith("go to the ")
    bad = subprocess.run([sys.executable, "-m", "gsmn.cli", "eval", "--system", "nope", "--env-ids", "70"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "unknown system" in bad.stderr
    # `gsmn analyze table1` makes the Table 1 markdown from such files, and refuses rows on other environments.
    oracle, progress = tmp_path / "oracle.json", tmp_path / "oracle.progress.jsonl"
    subprocess.run([sys.executable, "-m", "gsmn.cli", "eval", "--system", "oracle", "--env-ids", "70,71,72", "--json",
                    str(oracle), "--preset", "tiny", "--progress", str(progress)], check=True, capture_output=True)
    # the progress lines (what the dashboard reads) carry the steps inside the success region, without trajectories
    from app.jobs.results import region_steps_of

    lines = [json.loads(x) for x in progress.read_text().splitlines()]
    records = {e["env_id"]: e for e in json.loads(oracle.read_text())["episodes"]}
    assert [x["done"] for x in lines] == [1, 2, 3] and all("trajectory" not in x for x in lines)
    assert all(x["region_stop_p"] is None and "stop_probabilities" not in x for x in lines)  # the expert has none
    assert any(r["success"] for r in records.values())
    for line in lines:
        record = records[line["env_id"]]
        assert line["region_steps"] == region_steps_of(record, TINY.task.success_radius)
        if record["success"]:  # it said STOP inside the region: the last observation is one of its steps
            assert line["region_steps"][-1] == len(record["trajectory"]) - 1
    table1 = [sys.executable, "-m", "gsmn.cli", "analyze", "table1"]
    table = subprocess.run([*table1, str(out), str(oracle), "--label", "oracle=The expert"],
                           capture_output=True, text=True)
    assert table.returncode == 0, table.stderr
    rows = table.stdout.strip().splitlines()
    assert len(rows) == 4 and rows[2].startswith("| Random landmark | ") and rows[3].startswith("| The expert | ")
    oracle_summary = json.loads(oracle.read_text())["summary"]
    assert f"| {oracle_summary['success']:.2f} " in rows[3] and "| 87.87 (86.47) |" in rows[3]
    # `gsmn analyze regions`: every success entered the success region; the oracle's stops are its successes.
    counts = subprocess.run([sys.executable, "-m", "gsmn.cli", "analyze", "regions", f"oracle={oracle}",
                             f"random={out}"], capture_output=True, text=True)
    assert counts.returncode == 0, counts.stderr
    for name, path in (("oracle", oracle), ("random", out)):
        episodes = json.loads(path.read_text())["episodes"]
        row = next(r for r in counts.stdout.splitlines() if r.startswith(f"| {name} |")).strip("| ").split(" | ")
        successes, entered = int(row[2]), int(row[3])
        assert successes == sum(e["success"] for e in episodes) and entered >= successes
        assert row[7] == ("-" if entered == successes else "not kept")  # neither keeps a P(stop)
    assert "entered: only oracle" in counts.stdout
    # `gsmn analyze compare`: episode by episode, what the expert fixed and broke beside random-landmark.
    compare = [sys.executable, "-m", "gsmn.cli", "analyze", "compare", "--name", "three"]
    compared = subprocess.run([*compare, "--before", str(out), "--after", str(oracle)], capture_output=True, text=True)
    assert compared.returncode == 0, compared.stderr
    before = {e["env_id"]: e["success"] for e in json.loads(out.read_text())["episodes"]}
    after = {e["env_id"]: e["success"] for e in json.loads(oracle.read_text())["episodes"]}
    fixed, broken = sum(after[i] and not before[i] for i in before), sum(before[i] and not after[i] for i in before)
    assert f"Fixed {fixed}, broken {broken} (landmark success: " in compared.stdout
    rows = compared.stdout.splitlines()
    assert rows[2].startswith("| three (3) | before: ") and rows[3].startswith("| three (3) | after: ")
    assert f"| {oracle_summary['success']:.2f} (" in rows[3]
    d["env_ids"] = [70, 71]
    other = tmp_path / "other.json"
    other.write_text(json.dumps(d))
    mixed = subprocess.run([*table1, str(oracle), str(other)], capture_output=True, text=True)
    assert mixed.returncode == 2 and "different environments" in mixed.stderr
    mixed = subprocess.run([*compare, "--before", str(oracle), "--after", str(other)], capture_output=True, text=True)
    assert mixed.returncode == 2 and "different environments" in mixed.stderr


@pytest.mark.slow
def test_cli_eval_stopped_by_sigterm_resumes_where_it_stopped(tmp_path):
    """`gsmn eval --json F` keeps each finished episode in F.partial.jsonl; after SIGTERM mid-run, a second run
    refuses to overwrite it, `--resume` flies only the rest and writes the same F as an uninterrupted run, and other
    settings are refused."""
    import signal
    import time

    base = [sys.executable, "-m", "gsmn.cli", "eval", "--system", "oracle", "--env-ids", "0:80", "--preset", "tiny",
            "--task.horizon", "20"]
    whole = tmp_path / "whole.json"
    subprocess.run([*base, "--json", str(whole)], check=True, capture_output=True)
    assert not (tmp_path / "whole.json.partial.jsonl").exists()  # removed once the JSON is written
    out, progress = tmp_path / "out.json", tmp_path / "progress.jsonl"
    partial = tmp_path / "out.json.partial.jsonl"
    proc = subprocess.Popen([*base, "--json", str(out)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while not partial.exists() or len(partial.read_text().splitlines()) < 3:  # the settings and 2 episodes
            assert proc.poll() is None and time.monotonic() < deadline, "eval ended or stalled before 2 episodes"
            time.sleep(0.01)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 128 + signal.SIGTERM
    finally:
        if proc.poll() is None:
            proc.kill()
    assert not out.exists()
    kept = len(partial.read_text().splitlines()) - 1
    assert 2 <= kept < 80
    again = subprocess.run([*base, "--json", str(out)], capture_output=True, text=True)
    assert again.returncode == 2 and "pass --resume" in again.stderr
    assert len(partial.read_text().splitlines()) - 1 == kept  # saved work untouched
    other = subprocess.run([*base, "--json", str(out), "--resume", "--task.success-radius", "5"],
                           capture_output=True, text=True)
    assert other.returncode == 2 and "other settings (config)" in other.stderr
    other = subprocess.run([*base[:5], "random-point", *base[6:], "--json", str(out), "--resume"],
                           capture_output=True, text=True)
    assert other.returncode == 2 and "other settings (system)" in other.stderr
    other = subprocess.run([*base[:6], "--env-ids", "0:90", *base[8:], "--json", str(out), "--resume"],
                           capture_output=True, text=True)
    assert other.returncode == 2 and "other settings (env_ids)" in other.stderr
    resumed = subprocess.run([*base, "--json", str(out), "--resume", "--progress", str(progress)],
                             capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert f"resuming: {kept} of 80 episodes" in resumed.stderr and f"{80 - kept} flown in" in resumed.stdout
    a, b = json.loads(whole.read_text()), json.loads(out.read_text())
    assert b["env_ids"] == a["env_ids"] == list(range(80))
    assert b["episodes"] == a["episodes"] and b["summary"] == a["summary"]
    assert [json.loads(x)["done"] for x in progress.read_text().splitlines()] == list(range(1, 81))
    assert not partial.exists()
    with pytest.raises(subprocess.CalledProcessError):  # --resume needs the file it resumes into
        subprocess.run([*base, "--resume"], check=True, capture_output=True)


def test_learned_systems_load_from_checkpoints(tmp_path):
    from gsmn.model.checkpoint import CheckpointError, save_checkpoint
    from gsmn.model.models import build_model
    from gsmn.model.vocabulary import Vocabulary

    vocabulary = Vocabulary.default()
    save_checkpoint(tmp_path / "gsmn", build_model("gsmn", TINY, vocabulary), TINY, vocabulary)
    policy = make_policy("gsmn", TINY, tmp_path / "gsmn")
    assert policy.needs_images and policy.model.kind == "gsmn"
    with Env(TINY) as env:
        record = rollout(env, policy, task_for_env(70, TINY), horizon=3)
    assert record.system == "gsmn" and len(record.actions) >= 1
    with pytest.raises(ValueError, match="not 'gs-fpv'"):
        make_policy("gs-fpv", TINY, tmp_path / "gsmn")
    with pytest.raises(CheckpointError, match="missing"):
        make_policy("gsmn", TINY, tmp_path / "missing")


@pytest.mark.parametrize("system", ["gsmn", "gs-fpv-mem", "gs-fpv", "gsmn-no-plan"])
def test_each_shipped_checkpoint_flies_as_its_own_system(system):
    """`gsmn eval --system S` with no --checkpoint flies checkpoints/S: it must hold an S model that runs."""
    policy = make_policy(system, TINY)
    assert policy.model.kind == system
    config = policy.config
    with Env(config) as env:
        record = rollout(env, policy, task_for_env(70, config), horizon=3)
    assert record.system == system and record.actions
    assert all(math.isfinite(v) for action in record.actions for v in action[:2])


@pytest.mark.slow
def test_stop_threshold_analysis_replays_a_recorded_evaluation_at_lower_thresholds(tmp_path, untrained_checkpoint):
    """`gsmn analyze stop-threshold`: at 0.5 it reproduces the recorded outcomes; at a lower threshold each episode
    stops at the first step whose recorded P(stop) is above it, and is scored there; ensembles are refused."""
    from gsmn.attribution import load_trace, trace_path
    from gsmn.config import with_overrides
    from gsmn.task.metrics import success

    config = with_overrides(TINY, {"task.horizon": "20"})
    folder = untrained_checkpoint
    records = evaluate("gsmn", [70, 71], config, folder, record_dir=tmp_path / "rec")
    results = tmp_path / "eval.json"
    results.write_text(json.dumps(results_dict("gsmn", str(folder), records, config, 1.0, 1)))
    p = {r.env_id: load_trace(trace_path(tmp_path / "rec", r.env_id)).stop_probability for r in records}
    # the record keeps the P(stop) the policy acted on: here the recording's, step for step
    assert all(np.array_equal(np.float32(r.stop_probabilities), p[r.env_id]) for r in records)
    tau = float(np.median(np.concatenate(list(p.values()))))  # about half the steps are above it
    assert 0 < tau < 0.5
    script = [sys.executable, "-m", "gsmn.cli", "analyze", "stop-threshold"]
    run = subprocess.run([*script, str(results), str(tmp_path / "rec"), "--taus", "0.5", str(tau)],
                         capture_output=True, text=True)
    assert run.returncode == 0, run.stderr
    rows = {line.split(" | ")[0].strip("| "): line.split(" | ") for line in run.stdout.splitlines()
            if line.startswith("| 0")}
    assert rows["0.5"][1] == f"{50.0 * sum(r.success for r in records):.1f} % ({sum(r.success for r in records)})"
    assert rows["0.5"][3] == str(sum(r.stopped for r in records))
    expected_ok, expected_stops = 0, 0
    for r in records:
        above = np.flatnonzero(p[r.env_id] > tau)
        t = int(above[0]) if above.size else len(r.trajectory) - 1
        expected_stops += bool(above.size) or r.stopped
        expected_ok += success(r.trajectory[t][:2], (r.landmark_x, r.landmark_y), (r.start_x, r.start_y), r.side,
                               config.task.success_radius)
    assert rows[f"{tau:g}"][1].endswith(f"({expected_ok})") and rows[f"{tau:g}"][3] == str(expected_stops)
    assert expected_stops == 2  # both stop early at this threshold
    # the file's own P(stop) alone gives the same table
    alone = subprocess.run([*script, str(results), "--taus", "0.5", str(tau)],
                           capture_output=True, text=True)
    assert alone.returncode == 0 and alone.stdout.splitlines()[1:] == run.stdout.splitlines()[1:], alone.stderr
    base_ok = sum(r.success for r in records)
    chosen = (0.5, base_ok) if base_ok >= expected_ok else (tau, expected_ok)  # ties go to the higher tau
    assert f"most successes (ties: the higher tau): tau {chosen[0]:g}, {chosen[1]} of 2" in alone.stdout
    # --write: the evaluation as flown at tau, each episode cut at its STOP, for `analyze table1` and the dashboard
    flown = tmp_path / "at_tau.json"
    wrote = subprocess.run([*script, str(results), "--taus", str(tau), "--write", str(tau),
                            str(flown)], capture_output=True, text=True)
    assert wrote.returncode == 0, wrote.stderr
    at_tau = json.loads(flown.read_text())
    assert at_tau["stop_threshold"] == tau and sum(e["success"] for e in at_tau["episodes"]) == expected_ok
    assert at_tau["summary"]["success"] == pytest.approx(50.0 * expected_ok)
    for e, r in zip(at_tau["episodes"], records, strict=True):
        t = int(np.flatnonzero(p[r.env_id] > tau)[0])  # both stop early at this threshold (above)
        assert e["stopped"] and e["steps"] == t and len(e["trajectory"]) == len(e["actions"]) == t + 1
        assert e["actions"][-1][2] and (e["final_x"], e["final_y"]) == tuple(r.trajectory[t][:2])
    again = subprocess.run([*script, str(flown)], capture_output=True, text=True)
    assert again.returncode == 2 and "re-scored at tau" in again.stderr
    # an ensemble keeps the mean P(stop) it acted on, so its file is scored too; its recording alone is refused
    ensemble = evaluate("gsmn", [70], config, folder, mirror_ensemble=True)
    (tmp_path / "ens.json").write_text(json.dumps(results_dict("gsmn", str(folder), ensemble, config, 1.0, 1,
                                                               mirror_ensemble=True)))
    assert len(ensemble[0].stop_probabilities) == len(ensemble[0].actions)
    members = ensemble[0].member_stop_probabilities  # and the two copies' own, step by step
    assert len(members) == len(ensemble[0].actions) and all(len(m) == 2 for m in members)
    assert np.allclose(np.mean(members, axis=1), ensemble[0].stop_probabilities)
    assert records[0].member_stop_probabilities is None  # a single network has no members
    back = EpisodeRecord.from_dict(json.loads(json.dumps(ensemble[0].to_dict())))
    assert back.member_stop_probabilities == ensemble[0].member_stop_probabilities
    scored = subprocess.run([*script, str(tmp_path / "ens.json")], capture_output=True, text=True)
    assert scored.returncode == 0 and f"({int(ensemble[0].success)})" in scored.stdout.splitlines()[3], scored.stderr
    older = json.loads(results.read_text())  # a file written before P(stop) was kept
    for e in older["episodes"]:
        del e["stop_probabilities"]
    (tmp_path / "older.json").write_text(json.dumps(older))
    needs = subprocess.run([*script, str(tmp_path / "older.json")], capture_output=True, text=True)
    assert needs.returncode == 2 and "give its --record folder" in needs.stderr
    older["mirror_ensemble"] = True
    (tmp_path / "mirrored.json").write_text(json.dumps(older))
    refused = subprocess.run([*script, str(tmp_path / "mirrored.json"), str(tmp_path / "rec")],
                             capture_output=True, text=True)
    assert refused.returncode == 2 and "one network's P(stop)" in refused.stderr


def test_region_counts_counts_the_stops_an_ensembles_mean_took_away(tmp_path):
    """`gsmn analyze regions` on a file that keeps an ensemble's members' P(stop): a failure that flew through the
    success region is counted when one member alone was above 0.5 there and the mean was not, and only then."""
    from gsmn.task.metrics import side_of

    landmark, start, inside, outside = (10.0, 10.0), (10.0, 0.0), (12.0, 9.0), (25.0, 25.0)
    side = side_of(landmark, start, inside)

    def episode(env_id: int, members: list[tuple[float, float]]) -> dict:
        path = [(*start, 5.0, 0.0), (*inside, 5.0, 0.0), (*outside, 5.0, 0.0)]
        return {"env_id": env_id, "landmark_x": landmark[0], "landmark_y": landmark[1], "start_x": start[0],
                "start_y": start[1], "side": side, "success": False, "stopped": False, "trajectory": path,
                "actions": [(1.0, 0.0, False)] * 3, "stop_probabilities": [sum(m) / 2 for m in members],
                "member_stop_probabilities": members}

    taken = episode(1, [(0.0, 0.0), (0.1, 0.8), (0.9, 0.9)])  # in the region: the mirrored copy alone said STOP
    kept = episode(2, [(0.0, 0.0), (0.45, 0.45), (0.9, 0.0)])  # nobody above 0.5 in the region (only outside)
    path = tmp_path / "ens.json"
    path.write_text(json.dumps({"episodes": [taken, kept]}))
    run = subprocess.run([sys.executable, "-m", "gsmn.cli", "analyze", "regions", f"ens={path}"], capture_output=True,
                         text=True)
    assert run.returncode == 0, run.stderr
    assert "| ens | 2 | 0 | 2 |" in run.stdout
    assert ("ens: of 2 failures that flew through the region, 1 had a step there at which a member alone would have "
            "said STOP but the mean did not (per member: 0, 1)") in run.stdout


def test_a_partial_evaluation_saved_before_a_setting_existed_resumes_with_the_setting_it_flew(tmp_path):
    """Baked shadows became the default after evaluations had been written without `camera.shadow_method`: a
    partial file (or a piece to merge) without it reads as MuJoCo's shadow passes, the look it flew, so it resumes
    or merges under that look and is refused under another, naming the settings."""
    from gsmn.config import RunConfig, with_overrides
    from gsmn.evaluation import PartialResults

    mujoco = with_overrides(RunConfig(), {"camera.shadow_method": "mujoco"})
    old = mujoco.to_dict()
    del old["camera"]["shadow_method"]
    record = evaluate("oracle", [70], preset("tiny"))[0]
    path = tmp_path / "out.json"
    header = {"system": "oracle", "env_ids": [70, 71], "checkpoint": None, "config": old}
    Path(str(path) + ".partial.jsonl").write_text(json.dumps(header) + "\n" + json.dumps(record.to_dict()) + "\n")
    with pytest.raises(ValueError, match=r"other settings \(config\)"):
        PartialResults(path).open({**header, "config": RunConfig().to_dict()}, resume=True)
    assert PartialResults(path).open({**header, "config": mujoco.to_dict()}, resume=True) == [record]
    other = evaluate("oracle", [71], preset("tiny"))[0]
    piece = results_dict("oracle", None, [record], mujoco, 1.0, 1)
    assert merge_results([{**piece, "config": old}, results_dict("oracle", None, [other], mujoco, 1.0, 1)]
                         )["env_ids"] == [70, 71]
    with pytest.raises(ValueError, match="different settings"):
        merge_results([{**piece, "config": old}, results_dict("oracle", None, [other], RunConfig(), 1.0, 1)])
