"""The routes of comparisons and forks (`app.live.compare`): `POST /api/comparisons`, `GET /api/comparisons`,
`GET /api/comparisons/{id}`, `POST /api/episodes/{id}/fork`.

`app.api.app` includes `router` last.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter
from pydantic import BaseModel, Field

from app.api.deps import COMMAND_TIMEOUT, TheRunner
from app.api.models import (
    MAX_STEP,
    EpisodeCreated,
    EpisodeId,
    EpisodeSummary,
    Policy,
    WorldEditModel,
    intervention_of,
    summary,
    world_edits_of,
)
from app.api.schema import EnvId, Strict, Text, path_id, responses
from app.live.commands import NotFound
from app.live.compare import Comparison, ForkEpisode, PolicySpec, StartComparison
from gsmn.task.edits import MAX_EDITS

router = APIRouter()
ComparisonId = Annotated[int, path_id("comparison")]


class PolicySpecModel(Strict):
    policy: Policy = Field("model", description="who flies, as in POST /api/episodes")
    checkpoint: Text | None = Field(
        None, min_length=1, max_length=1000, description="a checkpoint name or folder; omitted: the "
                                    "default")
    instruction: Text | None = Field(None, max_length=500, description="this side's own instruction; omitted: the "
                                     "comparison's")


class ComparisonRequest(Strict):
    env_id: EnvId = Field(..., examples=[70])
    instruction: Text | None = Field(None, max_length=500, description="omitted: the environment's own")
    policies: list[PolicySpecModel] = Field(..., min_length=2, max_length=2, description="the two sides")


class ComparisonCreated(BaseModel):
    id: int
    episodes: list[int]


class ForkRequest(Strict):
    step: int = Field(..., ge=0, le=MAX_STEP, description="the step to fork at: the fork's steps 0..step-1 are the "
                      "original's, and it flies on from the original's exact state at this step")
    instruction: Text | None = Field(None, max_length=500, description="omitted: the original's")
    checkpoint: Text | None = Field(
        None, min_length=1, max_length=1000, description="omitted: the original's model")
    policy: Policy | None = Field(None, description="omitted: the original's")
    world_edits: list[WorldEditModel] = Field(
        [], max_length=MAX_EDITS, description="edits made to the original's world at this step, as on POST "
        "/api/episodes (the drone keeps its exact state; a landmark may not be put where the drone then is)")
    intervention: dict | None = Field(
        None, examples=[{"map": "goal", "with": "truth", "hold": True}], description="from this step on the model "
        "flies with a corrected map in place of its own: map semantic, relevance or goal; with truth, or painted "
        "(the model's own map with paint: [{op: peak or erase, x, y, radius}], relevance and goal only); hold true "
        "(every step, the default) or false (the true semantic map written once into the map it keeps integrating); "
        "docs/model.md, 'Interventions'")


class ComparisonModel(BaseModel):
    id: int
    status: str
    env_id: int
    episodes: list[EpisodeSummary]
    diverged_at: int | None = Field(description="the first step at which the drones are more than 1 m apart, or "
                                    "one says STOP and the other does not; null while they have not parted")
    succeeded: list[int] = Field(description="the ids of the episodes that succeeded")


def answer(c: Comparison) -> ComparisonModel:
    return ComparisonModel(id=c.id, status=c.status, env_id=c.episodes[0].env_id,
                           episodes=[summary(e) for e in c.episodes], diverged_at=c.diverged_at(),
                           succeeded=[e.id for e in c.episodes if e.result is not None and e.result.success])


@router.post("/api/comparisons", response_model=ComparisonCreated, status_code=201,
             responses=responses(400, 409, 422, 503),
             summary="Fly one environment with two policies side by side (they step together)")
def create_comparison(request: ComparisonRequest, runner: TheRunner) -> ComparisonCreated:
    specs = [PolicySpec(p.policy, p.checkpoint, p.instruction) for p in request.policies]
    c = runner.call(StartComparison(request.env_id, request.instruction, specs), COMMAND_TIMEOUT)
    return ComparisonCreated(id=c.id, episodes=[e.id for e in c.episodes])


@router.get("/api/comparisons", response_model=list[ComparisonModel], summary="Comparisons kept in memory")
def list_comparisons(runner: TheRunner) -> list[ComparisonModel]:
    return [answer(c) for c in list(runner.pairs.store.values())]


@router.get("/api/comparisons/{comparison_id}", response_model=ComparisonModel, responses=responses(404, 422),
            summary="Both episodes' status and results, and the step at which they part")
def get_comparison(comparison_id: ComparisonId, runner: TheRunner) -> ComparisonModel:
    c = runner.comparison(comparison_id)
    if c is None:
        raise NotFound(f"no comparison {comparison_id} (comparisons are kept in memory, the oldest dropped)")
    return answer(c)


@router.post("/api/episodes/{episode_id}/fork", response_model=EpisodeCreated, status_code=201,
             responses=responses(400, 404, 409, 422, 503),
             summary="Fly on from step t of a finished episode, with another instruction, policy or checkpoint")
def fork(episode_id: EpisodeId, request: ForkRequest, runner: TheRunner):
    e = runner.call(ForkEpisode(episode_id, request.step, request.instruction, request.checkpoint,
                                request.policy, world_edits=world_edits_of(request.world_edits),
                                intervention=intervention_of(request.intervention)), COMMAND_TIMEOUT)
    return EpisodeCreated(id=e.id, status=e.status, env_id=e.env_id, instruction=e.instruction,
                          policy=e.policy)
