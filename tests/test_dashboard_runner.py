"""The dashboard's runner (tiny preset, an untrained checkpoint): episodes through the one rollout function,
per-step recordings, pause / single step / resume, preemption, counterfactual grounding, and errors that say
what was wrong without stopping the runner."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import torch
from support import until

from app.live.commands import (
    Conflict,
    Ground,
    NotFound,
    Resume,
    RunnerError,
    RunnerListener,
    SetSpeed,
    ShowEnv,
    StartEpisode,
    StepOnce,
)
from app.live.fixtures import make_untrained_checkpoint
from app.live.recording import CANCELLED, FINISHED, PAUSED
from app.live.runner import Runner
from app.render.colors import decode_image
from gsmn.config import preset

pytestmark = pytest.mark.slow


def wait_for(condition, timeout: float = 90.0, what: str = "condition") -> None:
    until(condition, timeout, what, every=0.02)


class Recorder(RunnerListener):
    def __init__(self):
        self.events: list[tuple] = []

    def on_world(self, shown):
        self.events.append(("world", shown.world.env_id))

    def on_episode_start(self, episode):
        self.events.append(("start", episode.id))

    def on_step(self, episode, record):
        self.events.append(("step", episode.id, record.step))

    def on_episode_end(self, episode):
        self.events.append(("end", episode.id, episode.status))


@pytest.fixture(scope="module")
def runner(tmp_path_factory, untrained_checkpoint):
    torch.set_num_threads(1)
    folder = untrained_checkpoint
    r = Runner(preset("tiny"), checkpoint=str(folder), require_checkpoint=True,
               checkpoints_root=tmp_path_factory.mktemp("empty")).start()
    yield r
    r.close()


def test_model_episode_records_every_step(runner):
    recorder = Recorder()
    runner.listeners.append(recorder)
    try:
        runner.call(ShowEnv(70))
        episode = runner.call(StartEpisode(70, None, "model"))
        wait_for(lambda: not episode.live, what="the episode to finish")
    finally:
        runner.listeners.remove(recorder)
    assert episode.status == FINISHED and episode.result is not None
    n = len(episode.steps)
    assert n == episode.result.steps + 1  # an observation per action flown, plus the last one
    assert [s.step for s in episode.steps] == list(range(n))
    kinds = [e[0] for e in recorder.events]
    assert kinds[0] == "world" and kinds[1] == "start" and kinds[-1] == "end" and kinds.count("step") == n
    first = episode.steps[0]
    assert decode_image(first.camera_jpeg).shape == (144, 256, 3)
    m = first.maps
    assert m.semantic_w.dtype == np.float16 and m.semantic_w.shape == (32, 32, 32)
    assert m.relevance_w.shape == (3, 32, 32) and m.goal_w.shape == (2, 32, 32) and m.goal_r.shape == (2, 64, 64)
    assert 0.0 <= m.stop_probability <= 1.0
    assert episode.steps[0].v == pytest.approx(m.v)  # the model flew: its own action is the flown one
    assert episode.result.stop_probability == episode.steps[-1].maps.stop_probability
    assert all(s.stop_probability == s.maps.stop_probability for s in episode.steps)  # one network: one P(stop)
    assert episode.steps_per_second() > 0


def test_mirror_ensemble_flies_and_records_the_unmirrored_maps(runner):
    """policy "mirror": the model as a test-time mirror ensemble. The flown actions are the ensemble's, the
    recorded maps and the model's own action are the unmirrored copy's, so the two differ."""
    episode = runner.call(StartEpisode(70, None, "mirror"))
    wait_for(lambda: not episode.live, what="the mirror-ensemble episode to finish")
    assert episode.status == FINISHED and episode.policy == "mirror" and episode.system == "gsmn"
    assert all(s.maps is not None for s in episode.steps)
    gaps = [abs(s.omega - s.maps.omega) + abs(s.v - s.maps.v) for s in episode.steps if not s.stop]
    assert max(gaps) > 1e-4
    # the STOP was decided on the mean of the two copies' P(stop), which the step keeps beside the copy's own
    assert all((s.stop_probability > 0.5) == s.stop for s in episode.steps)
    assert max(abs(s.stop_probability - s.maps.stop_probability) for s in episode.steps) > 1e-6
    assert episode.result.stop_probability == episode.steps[-1].stop_probability


def test_expert_flies_while_the_model_watches(runner):
    episode = runner.call(StartEpisode(70, None, "expert"))
    wait_for(lambda: not episode.live, what="the expert episode")
    assert episode.status == FINISHED and episode.system == "oracle"
    assert episode.result.success and episode.result.stopped and episode.result.goal_distance < 2.0
    assert all(s.maps is not None for s in episode.steps)  # the model's maps, although the expert flew
    assert all(s.stop_probability is None and s.decisive_stop_probability == s.maps.stop_probability
               for s in episode.steps)  # the expert decided; the watching model's P(stop) is what is shown


def test_grounding_the_flown_instruction_reproduces_the_recorded_maps(runner):
    episode = runner.call(StartEpisode(70, "go to the left side of the pumpkin", "expert"))
    wait_for(lambda: not episode.live, what="the episode")
    for step in (0, len(episode.steps) // 2, len(episode.steps) - 1):
        m = episode.steps[step].maps
        g = runner.call(Ground(episode.id, episode.instruction, step))
        assert g.step == step and g.instruction.side == "left"
        np.testing.assert_allclose(g.relevance_w, m.relevance_w.astype(np.float32), atol=2e-2, rtol=2e-2)
        np.testing.assert_allclose(g.goal_w, m.goal_w.astype(np.float32), atol=2e-2, rtol=2e-2)
        assert g.stop_probability == pytest.approx(m.stop_probability, abs=2e-2)
        assert g.seconds < 1.0
    other = runner.call(Ground(episode.id, "go to the right side of the pumpkin"))
    assert other.step == len(episode.steps) - 1 and other.instruction.side == "right"
    assert not np.allclose(other.goal_w, g.goal_w)  # another instruction, another goal map


def test_pause_single_step_and_resume(runner):
    episode = runner.call(StartEpisode(70, None, "model", paused=True))
    wait_for(lambda: len(episode.steps) == 1 and runner.live is episode, what="the first step")
    time.sleep(0.3)
    assert len(episode.steps) == 1 and episode.status == PAUSED  # held after the first step
    runner.call(StepOnce())
    wait_for(lambda: len(episode.steps) == 2, what="one more step")
    time.sleep(0.3)
    assert len(episode.steps) == 2
    g = runner.call(Ground(episode.id, "go to the front side of the pumpkin"))  # answered while paused
    assert g.step == 1
    runner.call(Resume())
    wait_for(lambda: not episode.live, what="the resumed episode")
    assert episode.status == FINISHED


def test_the_page_preempts_and_the_api_queues(runner):
    runner.call(SetSpeed(5.0))
    try:
        slow = runner.call(StartEpisode(70, None, "model"))
        queued = runner.call(StartEpisode(70, None, "expert"))
        wait_for(lambda: len(slow.steps) >= 2, what="the slow episode to fly")
        assert queued.status == "queued"
        runner.call(SetSpeed(None))
        page = runner.call(StartEpisode(71, None, "expert", preempt=True))
        wait_for(lambda: slow.status == CANCELLED, what="preemption")
        wait_for(lambda: not page.live and not queued.live, what="the page's and the queued episodes")
        assert page.status == FINISHED and queued.status == FINISHED
        assert page.finished < queued.finished  # the page's episode flew first, then the queued one
    finally:
        runner.call(SetSpeed(None))


@pytest.mark.parametrize("command, error, words", [
    (StartEpisode(-1), RunnerError, "env_id"),
    (StartEpisode(70, "fly to the moon"), RunnerError, "not a landmark: moon"),
    (StartEpisode(70, "Go to the LEFT side of the lighthouse!"), None, None),
    (StartEpisode(70, "go to the left side of the anvil"), RunnerError, "no anvil in this world"),
    (StartEpisode(70, "go to the pumpkin"), RunnerError, "no side"),
    (StartEpisode(70, None, "helicopter"), RunnerError, "policy"),
    (StartEpisode(70, None, "model", checkpoint="/nonexistent/ckpt"), RunnerError, "not one this dashboard offers"),
    (Ground(999, "go to the left side of the pumpkin"), NotFound, "no episode 999"),
    (ShowEnv(-5), RunnerError, "env_id"),
])
def test_bad_commands_say_what_was_wrong(runner, command, error, words):
    if error is None:
        episode = runner.call(command)
        assert episode.task.instruction.noun_phrase == "lighthouse"
        wait_for(lambda: not episode.live, what="the episode")
        return
    with pytest.raises(error, match=words):
        runner.call(command)
    assert runner.thread.is_alive()


def test_grounding_checks_its_step_and_words(runner):
    episode = runner.episodes.all()[-1]
    wait_for(lambda: not episode.live, what="the last episode")
    with pytest.raises(RunnerError, match="not recorded"):
        runner.call(Ground(episode.id, "go to the left side of the pumpkin", 10_000))
    with pytest.raises(RunnerError, match="not a landmark: spaceship"):
        runner.call(Ground(episode.id, "go to the left side of the spaceship"))


def test_without_a_checkpoint_the_expert_still_flies(tmp_path):
    r = Runner(preset("tiny"), checkpoint="gsmn", checkpoints_root=tmp_path).start()
    try:
        assert not r.has_model and "No model loaded" in r.checkpoint_message
        assert str(tmp_path / "gsmn") in r.checkpoint_message
        with pytest.raises(Conflict, match="no checkpoint to fly"):
            r.call(StartEpisode(70, None, "model"))
        episode = r.call(StartEpisode(70, None, "expert"))
        wait_for(lambda: not episode.live, what="the expert episode")
        assert episode.status == FINISHED and episode.checkpoint is None
        assert all(s.maps is None for s in episode.steps)
        with pytest.raises(Conflict, match="no semantic map"):
            r.call(Ground(episode.id, "go to the left side of the pumpkin"))
    finally:
        r.close()
    with pytest.raises(RunnerError, match="no checkpoint at"):
        Runner(preset("tiny"), checkpoint="gsmn", require_checkpoint=True, checkpoints_root=tmp_path).start()


def test_table2_checkpoints_are_offered_under_readable_names_and_fly(tmp_path):
    """`gsmn experiment table2` keeps each system in checkpoints/table2/<name>/ with its stage: the runner lists
    them one folder down, by the system's label and where its programme stands, and flies them by that name."""
    root = tmp_path / "checkpoints"
    make_untrained_checkpoint(root / "gsmn")
    for name, label, stage in (("no-ground", "GSMN without J_ground", {"stage": "supervised", "epoch": 4}),
                               ("no-plan", "GSMN without J_plan", {"stage": "dagger", "epoch": 15})):
        folder = make_untrained_checkpoint(root / "table2" / name)
        (folder / "stage.json").write_text(json.dumps({"system": name, "label": label, "epochs": 16 if
                                                       stage["stage"] == "supervised" else 15, **stage}))
    (root / "table2" / "no-plan" / "evaluation.json").write_text(json.dumps({"summary": {"success": 52.0,
                                                                                         "count": 300}}))
    (root / "table2" / "no-plan" / "stage.json").write_text(json.dumps(
        {**json.loads((root / "table2" / "no-plan" / "stage.json").read_text()), "evaluated": True}))
    r = Runner(preset("tiny"), checkpoint="gsmn", checkpoints_root=root).start()
    try:
        labels = {c.name: c.label for c in r.checkpoint_list()}
        assert labels == {"gsmn": "gsmn",
                          "table2/no-ground": "GSMN without J_ground (Table 2, in training: supervised epoch 4 of 16)",
                          "table2/no-plan": "GSMN without J_plan (Table 2: 52.0 % on 300 dev)"}
        episode = r.call(StartEpisode(70, None, "model", "table2/no-ground", paused=True))
        wait_for(lambda: len(episode.steps) == 1, what="the table2 model's first step")
        assert episode.status == PAUSED and episode.checkpoint == (root / "table2" / "no-ground").as_posix()
        assert episode.steps[0].maps is not None, "its maps are drawn"
    finally:
        r.close()
    # served by its path (`gsmn serve --checkpoint checkpoints/table2/no-plan`): listed once, as the default, by its
    # name (two menu entries of one label left the dashboard's page blank)
    r = Runner(preset("tiny"), checkpoint=root / "table2" / "no-plan", checkpoints_root=root).start()
    try:
        listed = r.checkpoint_list()
        assert [c.name for c in listed] == ["gsmn", "table2/no-ground", "table2/no-plan"]
        assert [c.name for c in listed if c.default] == ["table2/no-plan"]
    finally:
        r.close()
