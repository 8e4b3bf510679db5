"""The routes of the server and its episodes: health, the checkpoints it can fly, queueing an episode, an episode's
status, result and per-step data, cancelling it, and the episodes kept in memory (without an episode keeper).

They post the same runner commands as the page (`app.live.runner`), so both share one behaviour. `app.api.app`
includes the three routers in order: `router`, then the episode list (`in_memory` here, or `app.api.kept`'s when
the server keeps episodes in the record), then `episode_router`. The camera images, map layers and grounding of an
episode's steps are in `app.api.maps`.
"""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter
from pydantic import BaseModel, Field

from app.api.deps import COMMAND_TIMEOUT, MaybeKeeper, TheRunner, ViewerUrl, episode_or_404
from app.api.models import EpisodeCreated, EpisodeId, EpisodeSummary, Policy, WorldEditModel, summary, world_edits_of
from app.api.schema import EnvId, Strict, Text, responses
from app.live.commands import MAX_ENV_ID, CancelEpisode, StartEpisode
from app.live.models import FIRST_PERSON_KINDS
from app.render.truth import step_figures, went_wrong
from gsmn.task.edits import MAX_EDITS

router = APIRouter()  # health, checkpoints, queue an episode
in_memory = APIRouter()  # the episode list without a keeper
episode_router = APIRouter()  # one episode: its summary, cancelling it, its steps


class EpisodeRequest(Strict):
    env_id: EnvId = Field(..., description=f"environment id, 0 to {MAX_ENV_ID} (id % 100: 0-69 train, 70-84 test, "
                          "85-99 dev)", examples=[70])
    instruction: Text | None = Field(None, max_length=500, description="free text, e.g. 'go to the left side of "
                                     "the barrel'; omitted: the environment's own instruction")
    checkpoint: Text | None = Field(
        None, min_length=1, max_length=1000, description="a checkpoint name under checkpoints/ or a "
                                    "folder; omitted: the default checkpoint")
    policy: Policy = Field(
        "model", description="who flies: the model; the model as a test-time mirror ensemble (it also flies the "
        "mirror image of each step and the two actions are averaged; the maps are the unmirrored copy's); or the "
        "expert (with the model watching, when one is loaded)")
    world_edits: list[WorldEditModel] = Field(
        [], max_length=MAX_EDITS, description="edits to the environment's world, in order (gsmn.task.edits): move "
        "or remove a landmark by its index, add one from the catalogue; the instruction keeps its words and follows "
        "its landmark. An edit that cannot stand (off the field, on the drone, onto another landmark, the named "
        "landmark removed) is refused with 422 saying why",
        examples=[[{"op": "move", "landmark": 3, "x": 12.0, "y": 20.5}, {"op": "remove", "landmark": 5},
                   {"op": "add", "noun_phrase": "tank", "x": 4.0, "y": 9.0}]])


class ModelStep(BaseModel):
    v: float
    omega: float
    stop_probability: float


class TruthFigures(BaseModel):
    perception: float | None = Field(description="share of the seen landmark cells whose most likely class is right "
                                     "(null: nothing seen yet, or no trained perception head)")
    relevance: float | None = Field(description="AUC of P(named) for the named landmark's footprint, over seen cells "
                                    "(null: undefined, or no trained grounding head)")
    goal: float | None = Field(description="share of P(goal) inside the success region (null: no trained goal head)")


class StepModel(BaseModel):
    step: int
    time: float
    x: float
    y: float
    z: float
    yaw: float
    v: float
    omega: float
    stop: bool
    model: ModelStep | None = Field(description="the model's own action at this step, when a model watched")
    truth: TruthFigures | None = Field(None, description="the maps' agreement with the ground truth at this step "
                                       "(docs/compare.md), when a model watched")
    damaged: str | None = Field(None, description="why this step's maps cannot be read back from the record (its "
                                "bytes were damaged); null when they can")


class StepsResponse(BaseModel):
    episode_id: int
    status: str
    steps: list[StepModel]
    went_wrong: dict[str, int | None] | None = Field(
        None, description="for perception, relevance and goal: the step from which its figure stayed below its "
        "threshold to the end (null: it ended above it); null without model maps")


class CheckpointModel(BaseModel):
    name: str
    path: str
    kind: str | None
    created: str | None
    loaded: bool
    default: bool
    error: str | None
    metrics: dict
    label: str = Field(description="a readable name, e.g. 'GSMN without J_ground (Table 2: 52.0 % on 300 dev)'")
    live: bool = Field(True, description="whether it flies in the page's live view and POST /api/episodes: GSMN "
                       "kinds do; the first-person baselines (gs-fpv, gs-fpv-mem) build no map to show and are "
                       "evaluated (POST /api/evaluations) and fine-tuned (POST /api/runs) only")


class Health(BaseModel):
    status: Literal["ok"]
    model_loaded: bool
    checkpoint_message: str
    live_episode: int | None
    episodes: int
    viewer_url: str | None


# -- router -------------------------------------------------------------------------------------------------
@router.get("/api/health", response_model=Health, summary="Is the server up, and is a model loaded")
def health(runner: TheRunner, viewer_url: ViewerUrl) -> Health:
    live = runner.live
    return Health(status="ok", model_loaded=runner.has_model, checkpoint_message=runner.checkpoint_message,
                  live_episode=live.id if live else None, episodes=len(runner.episodes), viewer_url=viewer_url)


@router.get("/api/checkpoints", response_model=list[CheckpointModel], summary="Checkpoints the server can fly")
def checkpoints(runner: TheRunner) -> list[CheckpointModel]:
    return [CheckpointModel(**c.__dict__, live=c.kind not in FIRST_PERSON_KINDS) for c in runner.checkpoint_list()]


@router.post("/api/episodes", response_model=EpisodeCreated, status_code=201,
             responses=responses(400, 409, 422, 503), summary="Queue an episode; it flies after those before it")
def create_episode(request: EpisodeRequest, runner: TheRunner) -> EpisodeCreated:
    e = runner.call(StartEpisode(request.env_id, request.instruction, request.policy, request.checkpoint,
                                 world_edits=world_edits_of(request.world_edits)), COMMAND_TIMEOUT)
    return EpisodeCreated(id=e.id, status=e.status, env_id=e.env_id, instruction=e.instruction,
                          typed_instruction=e.typed, policy=e.policy)


# -- in_memory ----------------------------------------------------------------------------------------------
@in_memory.get("/api/episodes", response_model=list[EpisodeSummary], summary="Episodes kept in memory, oldest "
               "first")
def list_episodes(runner: TheRunner) -> list[EpisodeSummary]:
    return [summary(e) for e in runner.episodes.all()]


# -- episode_router -----------------------------------------------------------------------------------------
@episode_router.get("/api/episodes/{episode_id}", response_model=EpisodeSummary, responses=responses(404, 422),
                    summary="Status, steps and result")
def get_episode(episode_id: EpisodeId, runner: TheRunner, keeper: MaybeKeeper) -> EpisodeSummary:
    e = episode_or_404(runner, episode_id)
    if keeper is None:
        return summary(e)
    row = keeper.db.kept(e.id)  # what the record holds of it: never more than that is said to be kept
    return summary(e).model_copy(update={
        "pinned": bool(row["pinned"]) if row else False, "bytes": int(row["bytes"]) if row else None,
        "kept_steps": int(row["steps"]) if row else 0, "keeping": keeper.behind(e.id)})


@episode_router.delete("/api/episodes/{episode_id}", response_model=EpisodeSummary,
                       responses=responses(404, 409, 422, 503), summary="Cancel an episode: drop it from the queue, "
                       "or end it if it is flying")
def cancel_episode(episode_id: EpisodeId, runner: TheRunner) -> EpisodeSummary:
    return summary(runner.call(CancelEpisode(episode_id), COMMAND_TIMEOUT))


@episode_router.get("/api/episodes/{episode_id}/steps", response_model=StepsResponse,
                    responses=responses(404, 422),
                    summary="Per-step poses and actions (all recorded steps; complete once finished)")
def get_steps(episode_id: EpisodeId, runner: TheRunner) -> StepsResponse:
    e = episode_or_404(runner, episode_id)
    model = runner.models.get(e.checkpoint) if e.checkpoint else None
    records = list(e.steps)
    figures = step_figures(e, model.heads, runner.config.task.success_radius) if model else []
    figures = (figures + [None] * len(records))[:len(records)]
    steps = [StepModel(step=s.step, time=s.time, x=s.position[0], y=s.position[1], z=s.position[2], yaw=s.yaw,
                       v=s.v, omega=s.omega, stop=s.stop,
                       model=ModelStep(v=s.maps.v, omega=s.maps.omega, stop_probability=s.maps.stop_probability)
                       if s.maps else None, truth=TruthFigures(perception=f.perception, relevance=f.relevance,
                                                               goal=f.goal) if f else None, damaged=s.damaged)
             for s, f in zip(records, figures, strict=True)]
    return StepsResponse(episode_id=e.id, status=e.status, steps=steps,
                         went_wrong=went_wrong(figures, model.heads if model else None))
