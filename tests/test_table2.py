"""The Table 2 programme (gsmn/experiments/: recipe.py, programme.py, table.py, and table2.py its command line):
six systems that differ only in their switch, and a programme that survives losing its machine (run folders and
data gone) by resuming from its committed stage copies."""

from __future__ import annotations

import dataclasses
import fcntl
import json
import shutil
import subprocess
import sys
from pathlib import Path

from gsmn import evaluation
from gsmn.config import LossConfig, preset, with_overrides
from gsmn.experiments import programme
from gsmn.experiments.programme import Layout, collect_store, data_needed, run_system
from gsmn.experiments.recipe import (
    BY_NAME,
    RECIPES,
    SYSTEMS,
    System,
    environments,
    kept_partial,
    partial_path,
    read_stage,
    system_configs,
)
from gsmn.experiments.table import interval, orderings_markdown, pending, table1_markdown, table_markdown
from gsmn.model.losses import objectives_for
from gsmn.task.metrics import sign_test
from gsmn.training.store import EpisodeStore

pytestmark = __import__("pytest").mark.training  # its tier (tests/conftest.py), this file's imports left as they are


def _leaves(d: dict, prefix: str = "") -> dict:
    out = {}
    for key, value in d.items():
        if isinstance(value, dict):
            out.update(_leaves(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def test_the_six_systems_differ_from_the_control_only_in_their_switch():
    recipe = RECIPES["paper"]
    control = [_leaves(c.to_dict()) for c in system_configs(SYSTEMS[0], recipe)]
    assert SYSTEMS[0].switch == {} and SYSTEMS[0].kind == "gsmn"
    assert [s.name for s in SYSTEMS] == ["gsmn", "no-plan", "no-ground", "no-lang", "no-percept", "pose-noise",
                                         "no-ground-module", "no-plan-module", "gs-fpv", "gs-fpv-mem"]
    for system in SYSTEMS[1:]:
        for stage, (ours, theirs) in enumerate(zip(control, system_configs(system, recipe), strict=True)):
            theirs = _leaves(theirs.to_dict())
            differ = {k for k in ours if ours[k] != theirs[k]}
            assert differ == set(system.switch), (system.name, stage, differ)
            assert all(theirs[k] == v for k, v in system.switch.items())
    # the one switch each: off for an objective, the original code's 0.5 m for the pose noise
    assert {s.name: s.switch for s in SYSTEMS[1:]} == {
        "no-plan": {"loss.goal": False}, "no-ground": {"loss.grounding": False}, "no-lang": {"loss.language": False},
        "no-percept": {"loss.perception": False}, "pose-noise": {"model.pose_noise_std": 0.5},
        # the original code's ablations: the filter replaced by an identity, and its loss gone with it
        "no-ground-module": {"model.grounding_filter": False, "loss.grounding": False},
        "no-plan-module": {"model.goal_filter": False, "loss.goal": False},
        "gs-fpv": {}, "gs-fpv-mem": {}}  # the baselines differ in their kind alone
    # the -J_plan system's kind trains exactly the loss its config says: the kind adds nothing of its own
    no_plan = BY_NAME["no-plan"]
    loss = system_configs(no_plan, recipe)[0].loss
    assert objectives_for(no_plan.kind, loss) == loss == dataclasses.replace(LossConfig(), goal=False)
    assert [s.kind for s in SYSTEMS if s.name not in ("no-plan", "gs-fpv", "gs-fpv-mem")] == ["gsmn"] * 7
    assert [BY_NAME[n].kind for n in ("gs-fpv", "gs-fpv-mem")] == ["gs-fpv", "gs-fpv-mem"]
    # the recipe, shared by all: supervised at the paper's learning rate, DAggerFM at a lower one
    sup, dagger = control
    assert sup["train.epochs"] == recipe.epochs and sup["train.learning_rate"] == 1e-3
    assert dagger["train.learning_rate"] == recipe.dagger_learning_rate
    assert {k for k in sup if sup[k] != dagger[k]} == {"train.learning_rate"}
    # rendered as the first systems trained, with MuJoCo's shadow passes, whatever the library's default
    assert sup["camera.shadow_method"] == dagger["camera.shadow_method"] == recipe.shadow_method == "mujoco"
    assert recipe.base_config() == with_overrides(preset("paper"), {"camera.shadow_method": "mujoco"})


def test_the_recipe_reads_stage_copies_without_training_evaluation_or_torch():
    """The dashboard labels checkpoints with gsmn.experiments.recipe's `describe_stage` and `read_stage`: importing it
    loads neither training, evaluation, the model (torch) nor the programme."""
    code = "import sys, gsmn.experiments.recipe; print(' '.join(sorted(sys.modules)))"
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    heavy = ("torch", "gsmn.training", "gsmn.evaluation", "gsmn.model", "gsmn.experiments.programme")
    assert [m for m in loaded if m.startswith(heavy)] == []


def test_a_gpu_changes_only_where_the_systems_train_and_is_refused_before_anything_starts(tmp_path):
    """`--device cuda` moves the epochs onto a GPU, reading ahead on 4 threads, and changes nothing else, so a run
    started on the CPU resumes there and back (both are ADJUSTABLE); a machine without one says so at once."""
    from gsmn.training.run import ADJUSTABLE

    recipe = RECIPES["paper"]
    for system in SYSTEMS:
        for cpu, gpu in zip(system_configs(system, recipe), system_configs(system, recipe, 2, "cuda"),
                            strict=True):
            cpu, gpu = _leaves(cpu.to_dict()), _leaves(gpu.to_dict())
            assert {k for k in cpu if cpu[k] != gpu[k]} == {"train.device", "train.prefetch"}
            assert (gpu["train.device"], gpu["train.prefetch"], cpu["train.device"]) == ("cuda", 4, "cpu")
    assert {("train", "device"), ("train", "prefetch"), ("train", "threads")} <= set(ADJUSTABLE)
    import torch

    out = tmp_path / "out"
    for device, says in (("gpu", "--device 'gpu': train.device must be 'cpu', 'cuda' or 'cuda:N'"),
                         ("cuda", None if torch.cuda.is_available() else "--device cuda: torch")):
        if says is None:
            continue
        done = subprocess.run([sys.executable, "-m", "gsmn.cli", "experiment", "table2", "--recipe", "tiny", "--out",
                               str(out), "--ship", str(tmp_path / "ship"), "--device", device],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode != 0 and "Traceback" not in done.stderr, done.stderr
        assert says in done.stderr, done.stderr
        assert device == "gpu" or "no CUDA device" in done.stderr
        assert not out.exists()  # nothing collected, nothing started


def test_the_paired_figures_of_the_table():
    assert sign_test(0, 0) == 1.0
    assert abs(sign_test(10, 4) - 0.1796) < 1e-3  # the docs' example: 10 fixed against 4 broken
    assert sign_test(0, 10) < 0.002 and sign_test(5, 5) == 1.0
    low, high = interval(240, 300)
    assert 75.0 < low < 75.2 and 84.0 < high < 84.2  # p 0.8 at n 300


def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", *args], cwd=repo, capture_output=True, text=True, check=True).stdout


def test_a_progress_bar_times_the_stage_it_shows_not_the_programme():
    """Elapsed time, rate and ETA restart with each stage, and a resumed stage's earlier work is not read as speed."""
    import io

    from tqdm import tqdm

    bar = tqdm(total=1, file=io.StringIO(), mininterval=0)
    programme.show_progress(bar, "gsmn", "supervised epoch 1/16 train", 0, 600)
    bar.start_t -= 100  # 100 s into the epoch
    programme.show_progress(bar, "gsmn", "supervised epoch 1/16 train", 50, 600)
    assert "50/600 [01:40<18:20" in tqdm.format_meter(**bar.format_dict)  # 0.5 batches/s: 550 left in 1100 s
    programme.show_progress(bar, "gsmn", "evaluated", 150, 300)  # a resumed evaluation, half done before
    assert bar.format_dict["elapsed"] < 5 and bar.desc == "gsmn: evaluated" and bar.total == 300
    bar.start_t -= 10
    programme.show_progress(bar, "gsmn", "evaluated", 160, 300)
    meter = tqdm.format_meter(**bar.format_dict)
    assert "160/300 [00:10<02:20" in meter  # 10 episodes in 10 s, so 140 left in 140 s (not 160 in 10 s)
    programme.show_progress(bar, "gsmn", "evaluated", 20, 300)  # restarted from the stage copy: the count went back
    bar.start_t -= 10
    programme.show_progress(bar, "gsmn", "evaluated", 30, 300)
    assert "30/300 [00:10<04:30" in tqdm.format_meter(**bar.format_dict)  # 10 in 10 s, never a negative rate
    bar.close()


def test_the_programme_resumes_from_its_committed_stage_after_losing_its_machine(tmp_path, monkeypatch):
    """Supervised learning and one DAggerFM iteration, each stage copied and committed; then the machine is lost
    (run folders and expert data gone): a new start restores the DAggerFM run from the commit, rebuilds only the dev
    data, refills the DAggerFM dataset from the current mixture, finishes, and keeps a compact evaluation."""
    repo = tmp_path / "repo"
    repo.mkdir()
    _git(repo, "init", "-q")
    _git(repo, "config", "user.email", "t@example.org")
    _git(repo, "config", "user.name", "test")
    _git(repo, "commit", "-q", "--allow-empty", "-m", "start")
    layout = Layout(tmp_path / "runs", repo / "checkpoints" / "table2")
    recipe = dataclasses.replace(RECIPES["tiny"], eval_envs=1)
    control: System = SYSTEMS[0]
    ship = layout.shipped(control)

    assert data_needed(layout, recipe, [control]) == ("train", "dev", "seed")
    lines: list[str] = []
    stopped = run_system(control, layout, recipe, threads=1, commit=True, log=lines.append,
                         stop_after=lambda stage, state: stage == "dagger" and state.epoch == 1)
    assert stopped is None
    # the system collects each store when its next stage reads it: the seed data only on reaching DAggerFM
    collecting = [line for line in lines if line.startswith("collecting")]
    assert collecting == ["collecting the supervised data: 3 of 3 expert episodes to go, first ids first",
                          "collecting the dev data: 2 of 2 expert episodes to go, first ids first",
                          "collecting the DAggerFM seed data: 2 of 2 expert episodes to go, first ids first"]
    assert lines.index(collecting[2]) > lines.index("gsmn: kept supervised epoch 2 of 2 in " + str(ship))
    assert not (layout.out / control.name / "collect.json").exists()  # the progress bars' file, gone when done
    assert len(EpisodeStore(layout.data / "expert_seed")) == 2
    with open(layout.data / "expert_seed.lock") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)  # let go: this raises while it is held
    stage = json.loads((ship / "stage.json").read_text())
    assert (stage["stage"], stage["epoch"], stage["epochs"], stage["evaluated"]) == ("dagger", 1, 2, False)
    # committed only when a stage ends: the supervised stage's last epoch; a copy between two stage ends waits
    history = _git(repo, "log", "--format=%s").splitlines()
    assert history[0] == "table2: GSMN, supervised epoch 2 of 2 (stage copy for resuming)"
    assert "supervised epoch 1 of 2" not in "".join(history)
    assert _git(repo, "status", "--porcelain") != ""
    # ... until the work pauses: --keep-latest commits the copy there is (the one resume copy, replaced)
    programme.keep_latest(layout, [control], commit=True, log=lines.append)
    assert _git(repo, "log", "-1", "--format=%s").strip() == \
        "table2: GSMN, dagger iteration 1 of 2 (stage copy for resuming)"
    # one copy in the tree: a checkpoint with its Adam state (safetensors: no pickle) and the run's small files
    tracked = sorted(_git(repo, "ls-files", "checkpoints").split())
    assert tracked == sorted(f"checkpoints/table2/gsmn/{name}" for name in (
        "config.json", "meta.json", "optimizer.safetensors", "vocabulary.json", "weights.safetensors", "stage.json",
        "run/config.json", "run/log.jsonl", "run/state.json", "run/supervised_log.jsonl"))
    assert _git(repo, "status", "--porcelain") == ""
    # a DAggerFM copy keeps the supervised epochs' log (Figure 4's figures) beside its own
    supervised_log = (layout.run(control, "supervised") / "log.jsonl").read_text()
    assert [json.loads(line)["epoch"] for line in supervised_log.splitlines()] == [1, 2]
    assert (ship / "run" / "supervised_log.jsonl").read_text() == supervised_log

    shutil.rmtree(layout.out)  # the machine is lost: runs/ and data/ are gone
    assert data_needed(layout, recipe, [control]) == ("dev",), "the restored run needs only its validation data"
    lines.clear()
    result = run_system(control, layout, recipe, threads=1, commit=True, log=lines.append)
    assert [line for line in lines if line.startswith("collecting")] == [
        "collecting the dev data: 2 of 2 expert episodes to go, first ids first"]
    assert not (layout.data / "expert_train").exists() and len(EpisodeStore(layout.data / "expert_seed")) == 0
    assert "gsmn: restoring DAggerFM iteration 1 from " + str(ship) in lines
    assert any("refilling it with 2 rollouts of the current mixture policy" in line for line in lines)
    log = [json.loads(line) for line in (layout.run(control, "dagger") / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2] and log[1]["refilled"] == 2
    assert not (layout.run(control, "supervised")).exists(), "the supervised stage is not redone"
    assert (ship / "run" / "supervised_log.jsonl").read_text() == supervised_log  # carried on from the copy
    assert (layout.latest(control) / "run" / "supervised_log.jsonl").read_text() == supervised_log

    # the compact evaluation: figures per episode, no trajectories; committed with the last stage
    assert result == json.loads((ship / "evaluation.json").read_text())
    assert result["env_ids"] == environments(recipe)["eval"] and len(result["episodes"]) == 1
    episode = result["episodes"][0]
    assert {"env_id", "success", "goal_distance", "stage", "final_x"} <= set(episode) and "trajectory" not in episode
    assert (episode["stage"] is None) == episode["success"]
    assert json.loads((ship / "stage.json").read_text())["evaluated"] is True
    assert _git(repo, "log", "-3", "--format=%s").splitlines() == [
        "table2: GSMN, evaluated on 1 test environments (Table 1)", "table2: GSMN, evaluated on 1 dev environments",
        "table2: GSMN, dagger iteration 2 of 2 (stage copy for resuming)"]
    # finished: weights, config, vocabulary and meta, no optimizer state; a further start has nothing to do
    assert not list(ship.glob("optimizer.*"))
    assert programme.done(layout, control, recipe)
    assert run_system(control, layout, recipe, threads=1, commit=True, log=lines.append) == result
    # the control is also flown on Table 1's test environments, kept the same way
    test = json.loads((ship / "table1.json").read_text())
    assert test["split"] == "test" and test["env_ids"] == environments(recipe)["table1"] == [70]
    assert len(test["episodes"]) == 1 and "trajectory" not in test["episodes"][0]
    assert f"| GSMN, Table 2's recipe (`checkpoints/table2/gsmn`) | {test['summary']['success']:.2f} (" \
        in table1_markdown(layout.ship)
    assert _git(repo, "status", "--porcelain") == ""
    table = table_markdown(layout.ship)
    assert "| GSMN | " in table and "| GSMN without J_ground | not yet (not started) |" in table
    # a start after the end does nothing more
    assert run_system(control, layout, recipe, threads=1, log=lines.append) == result

    # the recipe extended by an iteration (as below the control gate): the run goes on from its saved state, the
    # further stage copy replaces the evaluations, and the new model is evaluated on dev; below the gate, no Table 1
    longer = dataclasses.replace(recipe, iterations=3, control_gate=101.0)
    assert data_needed(layout, recipe, [control]) == () and data_needed(layout, longer, [control]) == ("dev",)
    publish = programme.publish

    def killed_while_copying(run_root, folder, stage, supervised_log=None):  # after the run saved its state
        if folder == ship:
            raise KeyboardInterrupt
        publish(run_root, folder, stage, supervised_log)

    monkeypatch.setattr(programme, "publish", killed_while_copying)
    try:
        run_system(control, layout, longer, threads=1, commit=True, log=lines.append)
        raise AssertionError("the stage copy should not have been made")
    except KeyboardInterrupt:
        pass
    assert programme._state_epoch(layout.run(control, "dagger")) == 3 and read_stage(ship)["epoch"] == 2
    monkeypatch.setattr(programme, "publish", publish)
    lines.clear()
    extended = run_system(control, layout, longer, threads=1, commit=True, log=lines.append)  # copies, evaluates
    log = [json.loads(line) for line in (layout.run(control, "dagger") / "log.jsonl").read_text().splitlines()]
    assert [r["iteration"] for r in log] == [1, 2, 3]
    stage = json.loads((ship / "stage.json").read_text())
    assert (stage["epoch"], stage["epochs"], stage["evaluated"]) == (3, 3, True)
    assert extended == json.loads((ship / "evaluation.json").read_text()) and extended["summary"]["count"] == 1
    assert not (ship / "table1.json").exists(), "the old model's Table 1 evaluation went with its stage copy"
    assert programme.control_below_gate(layout, longer) == extended["summary"]["success"]
    assert lines[-1] == (f"gsmn: no Table 1 evaluation: the control flies {extended['summary']['success']:.1f} % "
                         "on dev, below the recipe's gate of 101 % (docs/training.md)")
    assert _git(repo, "log", "-2", "--format=%s").splitlines() == [
        "table2: GSMN, evaluated on 1 dev environments",
        "table2: GSMN, dagger iteration 3 of 3 (stage copy for resuming)"]
    assert _git(repo, "status", "--porcelain") == ""
    # a kill between the evaluation and its flag in stage.json: the next start sets the flag, flying nothing
    programme.write_stage(ship, {**read_stage(ship), "evaluated": False})
    lines.clear()
    assert run_system(control, layout, longer, threads=1, log=lines.append) == extended
    assert read_stage(ship)["evaluated"] is True and not any("flying" in line for line in lines)


def test_a_machine_lost_before_the_first_dagger_copy_resumes_from_the_supervised_one(tmp_path):
    """Between the end of supervised learning and DAggerFM's first stage copy the shipped stage is the last epoch's:
    a new machine restores it, collects the dev and seed data but not the supervised data, and starts DAggerFM."""
    layout = Layout(tmp_path / "runs", tmp_path / "ship")
    recipe = dataclasses.replace(RECIPES["tiny"], epochs=1, publish_every_iterations=2)
    control: System = SYSTEMS[0]
    run_system(control, layout, recipe, threads=1, log=lambda s: None,
               stop_after=lambda stage, state: stage == "dagger" and state.epoch == 1)
    assert read_stage(layout.shipped(control))["stage"] == "supervised", "no DAggerFM copy yet"
    shutil.rmtree(layout.out)
    assert data_needed(layout, recipe, [control]) == ("dev", "seed")
    lines: list[str] = []
    run_system(control, layout, recipe, threads=1, log=lines.append,
               stop_after=lambda stage, state: stage == "dagger" and state.epoch == 1)
    assert [line for line in lines if line.startswith("collecting")] == [
        "collecting the dev data: 2 of 2 expert episodes to go, first ids first",
        "collecting the DAggerFM seed data: 2 of 2 expert episodes to go, first ids first"]
    assert f"{control.name}: restoring supervised epoch 1 from {layout.shipped(control)}" in lines
    assert not (layout.data / "expert_train").exists()
    assert programme._state_epoch(layout.run(control, "dagger")) == 1


def test_keep_latest_ships_a_further_epoch_and_never_an_older_one(tmp_path):
    layout = Layout(tmp_path / "runs", tmp_path / "ship")
    control = SYSTEMS[0]

    def stage_folder(folder: Path, stage: str, epoch: int, weights: bytes) -> None:
        folder.mkdir(parents=True)
        (folder / "weights.safetensors").write_bytes(weights)
        (folder / "stage.json").write_text(json.dumps({"system": control.name, "stage": stage, "epoch": epoch,
                                                       "epochs": 16, "evaluated": False}))

    assert programme.keep_latest(layout, [control]) == []  # nothing finished yet
    stage_folder(layout.shipped(control), "supervised", 4, b"epoch 4")
    stage_folder(layout.latest(control), "supervised", 6, b"epoch 6")
    assert programme.keep_latest(layout, [control]) == [control.name]
    ship = layout.shipped(control)
    assert (ship / "weights.safetensors").read_bytes() == b"epoch 6"
    assert read_stage(ship)["epoch"] == 6
    assert not list(ship.parent.glob(".*"))  # no temporary folder left

    shutil.rmtree(layout.latest(control))
    stage_folder(layout.latest(control), "supervised", 5, b"epoch 5")  # behind the stage copy: left alone
    assert programme.keep_latest(layout, [control]) == []
    assert (ship / "weights.safetensors").read_bytes() == b"epoch 6"
    shutil.rmtree(layout.latest(control))
    stage_folder(layout.latest(control), "dagger", 1, b"iteration 1")  # DAggerFM is further than any epoch
    assert programme.keep_latest(layout, [control]) == [control.name]
    assert read_stage(ship)["stage"] == "dagger"

    # an evaluated copy is up to date at the same iteration; one further on (a recipe extended since) replaces it
    # with its evaluations, which measured the older model
    (ship / "evaluation.json").write_text("{}")
    (ship / "table1.json").write_text("{}")
    (ship / "stage.json").write_text(json.dumps({**read_stage(ship), "evaluated": True}))
    assert programme.keep_latest(layout, [control]) == []
    assert (ship / "evaluation.json").is_file() and read_stage(ship)["evaluated"] is True
    shutil.rmtree(layout.latest(control))
    stage_folder(layout.latest(control), "dagger", 2, b"iteration 2")
    assert programme.keep_latest(layout, [control]) == [control.name]
    assert (ship / "weights.safetensors").read_bytes() == b"iteration 2"
    assert read_stage(ship)["evaluated"] is False
    assert not (ship / "evaluation.json").exists() and not (ship / "table1.json").exists()


def test_below_the_control_gate_no_table1_evaluation_flies(tmp_path, monkeypatch):
    """The control's dev success below the recipe's gate stops Table 1's test evaluations (their models would be
    trained on under an extended recipe): none starts, and one under way stops before its next chunk."""
    layout = Layout(tmp_path / "runs", tmp_path / "ship")
    recipe = dataclasses.replace(RECIPES["tiny"], control_gate=60.0)
    control, no_plan = BY_NAME["gsmn"], BY_NAME["no-plan"]

    def evaluated(system: System, success: float | None, epochs: int = recipe.iterations) -> None:
        ship = layout.shipped(system)
        ship.mkdir(parents=True, exist_ok=True)
        (ship / "stage.json").write_text(json.dumps({"system": system.name, "stage": "dagger", "epoch": epochs,
                                                     "epochs": epochs, "evaluated": success is not None}))
        if success is not None:
            (ship / "evaluation.json").write_text(json.dumps({"summary": {"success": success}}))

    evaluated(control, None)
    assert programme.control_below_gate(layout, recipe) is None  # not yet known
    evaluated(control, 70.0)
    assert programme.control_below_gate(layout, recipe) is None
    evaluated(control, 50.0, epochs=recipe.iterations + 1)  # another recipe's evaluation says nothing of this one
    assert programme.control_below_gate(layout, recipe) is None
    evaluated(control, 50.0)
    assert programme.control_below_gate(layout, recipe) == 50.0

    evaluated(no_plan, 40.0)
    assert programme.describe(layout, no_plan, recipe) == (
        "evaluated on dev (the control is below the gate: no Table 1)", 1, 1)

    def no_flight(command, **kwargs):
        raise AssertionError(f"flew {command}")

    monkeypatch.setattr(programme.subprocess, "run", no_flight)
    asked: list[bool] = []
    assert programme.evaluate_system(no_plan, layout, recipe, threads=1, log=lambda s: None, split="test",
                                  stop=lambda: asked.append(True) or True) is None
    assert asked == [True]


def test_a_running_system_goes_on_from_a_further_stage_copy_shipped_from_elsewhere(tmp_path):
    """Epochs trained on another machine (a GPU's) and shipped while this machine's programme trains on: this run's
    older epoch never replaces them; it stops at that epoch's end and goes on from the further copy."""
    recipe = dataclasses.replace(RECIPES["tiny"], epochs=5)  # a stage copy at every epoch; stopped after the fourth
    here, elsewhere = Layout(tmp_path / "here", tmp_path / "ship"), Layout(tmp_path / "elsewhere", tmp_path / "ship")
    control: System = SYSTEMS[0]
    ship = here.shipped(control)
    for name in ("train", "dev"):
        collect_store(here, recipe, name, log=lambda s: None)
    shutil.copytree(here.data, elsewhere.data)
    away: list[str] = []

    def train_elsewhere(stage: str, state) -> bool:  # asked at each epoch's end here, once the epoch is kept
        if state.epoch == 1:  # meanwhile the other machine resumes from this epoch 1 and trains epochs 2 and 3
            assert run_system(control, elsewhere, recipe, threads=1, log=away.append,
                              stop_after=lambda stage, state: state.epoch == 3) is None
            assert read_stage(ship)["epoch"] == 3
        return state.epoch == 4

    lines: list[str] = []
    assert run_system(control, here, recipe, threads=1, log=lines.append, stop_after=train_elsewhere) is None
    assert f"{control.name}: restoring supervised epoch 1 from {ship}" in away
    assert any(line.startswith(f"{control.name}: {ship} holds a further stage") and line.endswith("not replaced")
               for line in lines), lines
    assert f"{control.name}: going on from the further stage copy in {ship}" in lines
    assert f"{control.name}: restoring supervised epoch 3 from {ship}" in lines
    # the copy and this run are the other machine's epochs 2 and 3, then this machine's epoch 4
    log = [json.loads(line) for line in (here.run(control, "supervised") / "log.jsonl").read_text().splitlines()]
    theirs = [json.loads(line) for line in (elsewhere.run(control, "supervised") / "log.jsonl").read_text()
              .splitlines()]
    assert [r["epoch"] for r in log] == [1, 2, 3, 4] and log[1:3] == theirs[1:3]
    assert read_stage(ship)["epoch"] == 4
    assert (ship / "run" / "log.jsonl").read_text() == (here.run(control, "supervised") / "log.jsonl").read_text()


def test_a_second_system_collecting_the_seed_data_flies_it_from_the_last_id(tmp_path, monkeypatch):
    """Two systems reaching DAggerFM together split the seed data: with the lock held by a live process,
    `collect_store` flies the ids from the last one; once that process is gone the lock is free again. Meanwhile
    the programme's progress bar reads how far the collection is."""
    layout = Layout(tmp_path / "runs", tmp_path / "ship")
    recipe = RECIPES["tiny"]
    lock = layout.data / "expert_seed.lock"
    lock.parent.mkdir(parents=True)
    holder = subprocess.Popen([sys.executable, "-c", "import fcntl, sys, time; f = open(sys.argv[1], 'a'); "
                               "fcntl.flock(f, fcntl.LOCK_EX); print('held', flush=True); time.sleep(120)", str(lock)],
                              stdout=subprocess.PIPE, text=True)
    store = EpisodeStore(layout.data / "expert_seed")
    try:
        assert holder.stdout.readline().strip() == "held"
        lines: list[str] = []
        progress = layout.out / SYSTEMS[0].name / "collect.json"
        progress.parent.mkdir()
        seen = []

        def write_json(path, value):  # what the programme's bar shows once the file is written
            real_write_json(path, value)
            seen.append(programme.describe(layout, SYSTEMS[0], recipe))

        real_write_json = evaluation.write_json
        monkeypatch.setattr(evaluation, "write_json", write_json)
        programme.collect_store(layout, recipe, "seed", workers=1, log=lines.append, progress=progress)
        assert lines == ["collecting the DAggerFM seed data: 2 of 2 expert episodes to go, last ids first"]
        assert seen == [("collecting the DAggerFM seed data", n, 2) for n in (0, 1, 2)] and not progress.exists()
        assert sorted(store.keys()) == [f"env_{e:06d}" for e in environments(recipe)["seed"]]
    finally:
        holder.kill()
        holder.wait()
    lines.clear()
    programme.collect_store(layout, recipe, "seed", workers=1, log=lines.append)
    assert lines == [], "nothing left to collect"
    store.path(store.keys()[0]).unlink()
    programme.collect_store(layout, recipe, "seed", workers=1, log=lines.append)  # its holder is gone: the lock is free
    assert lines == ["collecting the DAggerFM seed data: 1 of 2 expert episodes to go, first ids first"]


def test_a_row_not_yet_measured_says_where_its_system_stands(tmp_path):
    """Table 2 and Table 1's rows printed mid-programme name each unfinished system's last kept stage."""
    def stage(name: str, **fields) -> None:
        (tmp_path / name).mkdir()
        (tmp_path / name / "stage.json").write_text(json.dumps({"system": name, "evaluated": False, **fields}))

    stage("gsmn", stage="dagger", epoch=7, epochs=15)
    stage("no-plan", stage="dagger", epoch=15, epochs=15)
    stage("no-ground", stage="supervised", epoch=8, epochs=16)
    table, table1 = table_markdown(tmp_path), table1_markdown(tmp_path)
    assert "| GSMN | not yet (DAggerFM iteration 7 of 15) |" in table
    assert "| GSMN without J_plan | not yet (trained, not evaluated) |" in table
    assert "| GSMN without J_ground | not yet (supervised epoch 8 of 16) |" in table
    assert "| GSMN without J_lang | not yet (not started) |" in table
    assert "| GSMN, Table 2's recipe | not yet (DAggerFM iteration 7 of 15) |" in table1


def test_a_system_without_maps_has_its_failures_marked_not_attributed_not_counted_as_none(tmp_path):
    """GS-FPV has no map to attribute: its row says so instead of a zero at every stage."""
    for name, stages in (("gsmn", ["goal", None]), ("gs-fpv", [None, None])):
        episodes = [{"env_id": 85 + i, "success": stage is None and name == "gsmn", "stage": stage}
                    for i, stage in enumerate(stages)]
        summary = {"success": 50.0 if name == "gsmn" else 0.0, "landmark_success": 50.0, "mean_distance": 3.0,
                   "median_distance": 3.0}
        (tmp_path / name).mkdir()
        (tmp_path / name / "evaluation.json").write_text(json.dumps({"summary": summary, "episodes": episodes}))
    rows = {line.split(" | ")[0]: line for line in table_markdown(tmp_path).splitlines() if line.startswith("| GS")}
    assert rows["| GSMN"].endswith("| 0, 0, 1, 0 |")
    assert rows["| GS-FPV"].endswith("| not attributed (no maps) |")


def test_table1_rows_stand_beside_the_papers_with_the_paired_comparison(tmp_path):
    """Table 1's rows of the control and -J_plan in docs/results.md's columns, the paper's figures by model kind
    (-J_plan's are the paper's GSMN - J_goal), and -J_plan's paired comparison over the same environments."""
    def kept(name: str, outcomes: list[bool]) -> None:
        episodes = [{"env_id": 70 + i, "success": ok} for i, ok in enumerate(outcomes)]
        figures = {"success": 100.0 * sum(outcomes) / len(outcomes), "landmark_success": 50.0,
                   "mean_distance": 3.0, "median_distance": 2.0}
        (tmp_path / name).mkdir()
        (tmp_path / name / "table1.json").write_text(json.dumps({
            "system": name, "split": "test", "env_ids": [e["env_id"] for e in episodes], "episodes": episodes,
            "summary": {**figures, "count": len(episodes), "pruned": figures}}))

    kept("gsmn", [True, True, True, False])
    kept("no-plan", [False, False, True, True])
    lines = table1_markdown(tmp_path).splitlines()
    assert lines[2] == ("| GSMN, Table 2's recipe (`checkpoints/table2/gsmn`) | 75.00 (75.00) | 83.47 (87.21) | "
                        "50.00 (50.00) | 89.33 (93.38) | 3.00 (3.00) | 2.67 (2.24) | 2.00 (2.00) | 1.21 (1.12) |")
    assert lines[3].startswith("| GSMN without J_plan, Table 2's recipe (`checkpoints/table2/no-plan`) | 50.00 "
                               "(50.00) | 69.89 (71.03) |")
    assert lines[-1] == ("GSMN without J_plan against GSMN, paired over the same 4 environments: 1 fixed / 2 broken, "
                         f"sign test p {sign_test(1, 2):.2g}")


def test_an_evaluation_keeps_its_finished_chunks_for_a_new_machine(tmp_path, monkeypatch):
    """The evaluation flies EVAL_CHUNK environments at a time and keeps each finished chunk's compact episodes
    beside the stage copy; a machine lost mid-evaluation (run folder gone) flies only the rest."""
    layout = Layout(tmp_path / "runs", tmp_path / "ship")
    control: System = SYSTEMS[0]
    ship = layout.shipped(control)
    shutil.copytree(Path(__file__).resolve().parents[1] / "checkpoints" / "gsmn", ship)  # a GSMN checkpoint
    (ship / "stage.json").write_text(json.dumps({"system": "gsmn", "stage": "dagger", "epoch": 2, "epochs": 2,
                                                 "evaluated": False}))
    recipe = dataclasses.replace(RECIPES["tiny"], eval_envs=3)
    ids = environments(recipe)["eval"]
    monkeypatch.setattr(programme, "EVAL_CHUNK", 2)
    flights: list[list[str]] = []
    run = subprocess.run

    def lost_after_one_chunk(command, **kwargs):  # the machine goes while it flies the second chunk
        flights.append(command)
        if len(flights) > 1:
            raise KeyboardInterrupt
        return run(command, **kwargs)

    monkeypatch.setattr(programme.subprocess, "run", lost_after_one_chunk)
    lines: list[str] = []
    try:
        programme.evaluate_system(control, layout, recipe, threads=1, log=lines.append)
        raise AssertionError("the second chunk should not have flown")
    except KeyboardInterrupt:
        pass
    kept = json.loads(partial_path(ship, "dev").read_text())
    assert kept["env_ids"] == ids and [e["env_id"] for e in kept["episodes"]] == ids[:2]
    assert all("trajectory" not in e and "stage" in e for e in kept["episodes"])
    assert pending(ship) == "not yet (2 of 3 dev environments flown)"
    assert programme.describe(layout, control, recipe) == ("evaluating on dev", 2, 3)

    shutil.rmtree(layout.out)  # the machine is lost
    monkeypatch.setattr(programme.subprocess, "run", run)
    lines.clear()
    result = programme.evaluate_system(control, layout, recipe, threads=1, log=lines.append)
    assert lines == [f"gsmn: 2 of 3 dev environments kept in {partial_path(ship, 'dev')}",
                     "gsmn: flying 1 dev environments (2 of 3 done)"]
    assert [e["env_id"] for e in result["episodes"]] == ids and result["episodes"][:2] == kept["episodes"]
    assert result["summary"]["count"] == 3
    assert result["summary"]["success"] == 100 * sum(e["success"] for e in result["episodes"]) / 3

    # a partial evaluation of another stage copy (a recipe extended since) is not reused
    (ship / "stage.json").write_text(json.dumps({"system": "gsmn", "stage": "dagger", "epoch": 3, "epochs": 3,
                                                 "evaluated": False}))
    assert kept_partial(ship, "dev", ids) == {"episodes": []}
    assert pending(ship) == "not yet (trained, not evaluated)"


def test_the_programme_ends_when_the_control_is_below_the_gate(tmp_path, monkeypatch):
    """Once the control's process ends below the gate no further system starts, and the programme ends (status 1)
    when the running ones are done."""
    layout = Layout(tmp_path / "runs", tmp_path / "ship")
    recipe = dataclasses.replace(RECIPES["tiny"], control_gate=60.0)
    ship = layout.shipped(SYSTEMS[0])
    started: list[str] = []

    class Finished:  # a system's process, done at once (its pipeline is tested above): the control below the gate
        returncode = 0

        def __init__(self, command, **kwargs):
            started.append(command[command.index("--system") + 1])
            if started[-1] == "gsmn":
                ship.mkdir(parents=True)
                (ship / "stage.json").write_text(json.dumps({"system": "gsmn", "stage": "dagger", "evaluated": True,
                                                             "epoch": recipe.iterations, "epochs": recipe.iterations}))
                (ship / "evaluation.json").write_text(json.dumps({"summary": {"success": 50.0}}))

        def poll(self):
            return 0

    monkeypatch.setattr(programme.subprocess, "Popen", Finished)
    assert programme.run_programme(layout, recipe, "tiny", list(SYSTEMS)) == 1
    assert started == ["gsmn", "no-plan"]
    # started again: the control is done (not restarted) and its gate holds at once
    assert programme.run_programme(layout, recipe, "tiny", list(SYSTEMS)) == 1
    assert started == ["gsmn", "no-plan"]


def test_the_orderings_pair_the_ablations_and_split_what_each_breaks(tmp_path):
    """`--table`'s orderings: the measured ablations by drop, each pair's sign test over the same environments,
    and the control's successes each ablation breaks, by its attributed stage; pose noise is not an objective, so it
    is not ranked, only split."""
    def kept(name: str, outcomes: str, stages: str = "") -> None:
        stage = iter(stages.split())
        episodes = [{"env_id": 85 + i, "success": ok == "+", "stage": None if ok == "+" else next(stage)}
                    for i, ok in enumerate(outcomes)]
        (tmp_path / name).mkdir()
        (tmp_path / name / "evaluation.json").write_text(json.dumps({"system": name, "episodes": episodes}))

    assert orderings_markdown(tmp_path).startswith("Orderings: not yet")
    kept("gsmn", "+++++-", "goal")
    kept("no-plan", "+-+++-", "perception_or_grounding goal")  # first in SYSTEMS, the smaller drop: ranked second
    kept("no-percept", "--+++-", "goal perception goal")
    kept("no-lang", "-+++++", "goal")  # env 90 only in the control's evaluation: not paired
    (tmp_path / "no-lang" / "evaluation.json").write_text(json.dumps({"episodes": [
        {"env_id": 85 + i, "success": i > 0, "stage": None} for i in range(5)]}))  # flown without attribution
    kept("pose-noise", "------", "goal " * 6)
    lines = orderings_markdown(tmp_path).splitlines()
    assert lines == [
        "Ablations by success rate, the largest drop first (control 83.3 %): GSMN without J_percept (50.0 %), "
        "GSMN without J_plan (66.7 %), GSMN without J_lang (80.0 %)",
        "GSMN without J_plan succeeds where GSMN without J_percept fails in 1, the reverse in 0: sign test p 1",
        "GSMN without J_lang succeeds where GSMN without J_percept fails in 1, the reverse in 0: sign test p 1",
        "GSMN without J_lang succeeds where GSMN without J_plan fails in 1, the reverse in 1: sign test p 1",
        "GSMN without J_percept breaks 2 of the control's successes: goal 1, perception 1",
        "GSMN without J_plan breaks 1 of the control's successes: perception_or_grounding 1",
        "GSMN without J_lang breaks 1 of the control's successes: no stage attributed",
        "GSMN + pose noise breaks 5 of the control's successes: goal 5"]
