"""The response models that several route modules answer with: an episode as queued (`EpisodeCreated`) and its
summary (`EpisodeSummary`, made from a live episode by `summary`), and the path parameters they share.

The models only one route module uses live in that module (`app.api.episodes`, `app.api.maps`, `app.api.kept`,
`app.api.comparisons`, `app.api.jobs`); what every input may be is in `app.api.schema`.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, Field

from app.api.schema import Strict, Text, path_id
from app.live.commands import RunnerError
from app.live.recording import Episode, EpisodeResult
from gsmn.task.edits import EditError, parse_edits

MAX_STEP = 100_000  # more than any horizon
EpisodeId = Annotated[int, path_id("episode")]
Policy = Literal["model", "mirror", "expert"]

TYPED = "the instruction as typed, where one was (null: the environment's own); `instruction` is the template flown"


class EpisodeCreated(BaseModel):
    id: int
    status: str
    env_id: int
    instruction: str = Field(description="the template flown: what the model reads (gsmn.task.understand)")
    typed_instruction: str | None = Field(None, description=TYPED)
    policy: str


class ResultModel(BaseModel):
    success: bool
    landmark_success: bool
    goal_distance: float = Field(description="m, final position to the demonstration's goal")
    landmark_distance: float = Field(description="m, final position to the named landmark's centre")
    final_side: str = Field(description="quadrant of the final position around the named landmark")
    steps: int
    stopped: bool = Field(description="the policy said STOP (else the horizon ended the episode)")
    final_x: float
    final_y: float
    stop_probability: float | None = Field(description="the model's P(STOP) at the last step")


class WorldEditModel(Strict):
    op: Literal["move", "remove", "add"]
    landmark: int | None = Field(None, ge=0, le=63, description="move, remove: the landmark's index in the world")
    x: float | None = Field(None, allow_inf_nan=False, description="move, add: where its centre goes (m)")
    y: float | None = Field(None, allow_inf_nan=False)
    noun_phrase: Text | None = Field(None, max_length=60, description="add: a landmark of the catalogue, e.g. 'tank'")
    yaw: float | None = Field(None, allow_inf_nan=False, description="add: its heading (rad)")


def world_edits_of(models: list[WorldEditModel]) -> tuple:
    """The request's world edits, checked (gsmn.task.edits.parse_edits); a bad one is a RunnerError (422)."""
    try:
        return parse_edits([w.model_dump(exclude_none=True) for w in models])
    except EditError as err:
        raise RunnerError(str(err)) from err


def intervention_of(d: dict | None):
    """The request's map intervention, checked (gsmn.analysis.intervention.parse_intervention); a bad one is a
    RunnerError (422)."""
    if d is None:
        return None
    from gsmn.analysis.intervention import InterventionError, parse_intervention

    try:
        return parse_intervention(d)
    except InterventionError as err:
        raise RunnerError(str(err)) from err


class EpisodeSummary(BaseModel):
    id: int
    status: Literal["queued", "running", "paused", "finished", "cancelled", "failed"]
    env_id: int
    split: str
    instruction: str = Field(description="the template flown: what the model reads (gsmn.task.understand)")
    typed_instruction: str | None = Field(None, description=TYPED)
    landmark: str
    side: str
    goal_x: float
    goal_y: float
    policy: str
    system: str
    checkpoint: str | None
    steps: int = Field(description="steps recorded so far")
    horizon: int
    steps_per_second: float | None
    result: ResultModel | None
    error: str | None
    pinned: bool = Field(False, description="kept whatever the retention limit (PUT /api/episodes/{id}/pin)")
    created: float | None = Field(None, description="unix time it was queued or started flying")
    bytes: int | None = Field(None, description="what its steps take in the record (null: not written yet)")
    kept_steps: int | None = Field(None, description="the steps the record holds (null: no record); below `steps` "
                                   "while steps wait to be written, or where some could not be kept")
    keeping: str | None = Field(None, description="why some of its steps are not in the record (waiting for a full "
                                "disk, say, or given up); null when they all are")
    fork_of: int | None = Field(None, description="the episode it forks from (POST /api/episodes/{id}/fork); null "
                                "when it flew from the start")
    fork_step: int | None = Field(None, description="the step it forks at: its steps before it are the original's")
    comparison: int | None = Field(None, description="the comparison it flew in, by its id in the server that flew "
                                   "it (GET /api/comparisons/{id} while that server runs); null when none")
    comparison_side: Literal[1, 2] | None = Field(None, description="its side of that comparison: 1 the first "
                                                  "policy, 2 the one compared with")
    compared_with: int | None = Field(None, description="the other episode of that comparison")
    world_edits: list[dict] = Field([], description="the edits its world carries (POST /api/episodes' "
                                    "world_edits); empty: the environment's world as generated")
    intervention: dict | None = Field(None, description="the map the model flew with from its fork's step (POST "
                                      "/api/episodes/{id}/fork's intervention); null: its own maps")


def _result(r: EpisodeResult | None) -> ResultModel | None:
    return ResultModel(**r.__dict__) if r is not None else None


def summary(e: Episode) -> EpisodeSummary:
    i = e.task.instruction
    fork = (e.fork.episode_id, e.fork.step) if e.fork is not None else (None, None)
    return EpisodeSummary(id=e.id, status=e.status, env_id=e.env_id, split=e.task.world.split,
                          instruction=i.text, typed_instruction=e.typed, landmark=i.noun_phrase, side=i.side,
                          goal_x=i.goal_x, goal_y=i.goal_y,
                          policy=e.policy, system=e.system, checkpoint=e.checkpoint, steps=len(e.steps),
                          horizon=e.horizon, steps_per_second=e.steps_per_second(), result=_result(e.result),
                          error=e.error, created=e.created, fork_of=fork[0], fork_step=fork[1],
                          comparison=e.comparison, comparison_side=e.comparison_side,
                          compared_with=e.compared_with, world_edits=[w.to_dict() for w in e.world_edits],
                          intervention=e.intervention.to_dict() if e.intervention is not None else None)
