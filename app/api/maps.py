"""The routes of an episode's steps as pictures and maps: the camera image and every map layer at a step (the
model's maps and the ground truth, as PNG), and grounding another instruction on its semantic map at a step.

`app.api.app` includes `router` after `app.api.episodes`' routes; the steps' poses and actions as numbers are there.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from fastapi import APIRouter, Path
from fastapi.responses import Response
from pydantic import BaseModel, Field

from app.api.deps import COMMAND_TIMEOUT, TheRunner, episode_or_404
from app.api.models import MAX_STEP, EpisodeId
from app.api.schema import Id, Strict, Text, responses
from app.jobs.db import RecordError
from app.live.commands import Ground, Grounding, RunnerError
from app.live.recording import Episode, StepRecord
from app.render.colors import png_bytes, upscale
from app.render.export import heads_for
from app.render.layers import LAYERS, map_layers
from app.render.truth import TRUTH_LAYERS, episode_truth, truth_rgb
from gsmn.model.heads import positive_probability

router = APIRouter()
Step = Annotated[int, Path(ge=0, le=MAX_STEP, description="the step, from 0")]


class GroundRequest(Strict):
    episode_id: Id
    instruction: Text = Field(..., min_length=1, max_length=500, examples=["go to the right side of the barrel"])
    step: int | None = Field(None, ge=0, le=MAX_STEP, description="the step whose semantic map to use; omitted: "
                             "the latest")


class GroundResponse(BaseModel):
    episode_id: int
    step: int
    instruction: str = Field(description="the template grounded: what the model reads (gsmn.task.understand)")
    typed_instruction: str = Field(description="the instruction as typed")
    landmark: str
    side: str
    goal_x: float
    goal_y: float
    v: float = Field(description="m/s, the action the model would take")
    omega: float = Field(description="rad/s")
    stop_probability: float
    seconds: float = Field(description="time the grounding took (s)")
    relevance_probability: list[list[float]] | None = Field(
        description="P(named landmark) per world cell, north-up (null: a model trained without J_ground)")
    goal_probability: list[list[float]] | None = Field(
        description="P(goal) per world cell, north-up (null: a model trained without J_plan)")


def step_of(e: Episode, step: int) -> StepRecord:
    if not 0 <= step < len(e.steps):
        raise RunnerError(f"step {step} is not recorded: episode {e.id} has {len(e.steps)} steps")
    return e.steps[step]


@router.get("/api/episodes/{episode_id}/steps/{step}/camera.jpg", response_class=Response,
            responses={200: {"content": {"image/jpeg": {}}}, **responses(404, 422)},
            summary="The camera image at a step")
def get_camera(episode_id: EpisodeId, step: Step, runner: TheRunner) -> Response:
    return Response(step_of(episode_or_404(runner, episode_id), step).camera_jpeg, media_type="image/jpeg")


@router.get("/api/episodes/{episode_id}/steps/{step}/maps/{layer}.png", response_class=Response,
            responses={200: {"content": {"image/png": {}}}, **responses(404, 422)},
            summary="A map layer at a step as PNG (semantic, relevance, goal, goal_robot, or another map of the "
                    "model's output record by its name, e.g. coverage_w; or the ground truth: truth_semantic, "
                    "truth_relevance, truth_goal), 4x nearest-neighbour")
def get_map(episode_id: EpisodeId, step: Step, layer: Literal[LAYERS + TRUTH_LAYERS], runner: TheRunner) -> Response:
    e = episode_or_404(runner, episode_id)
    if layer not in LAYERS + TRUTH_LAYERS:
        raise RunnerError(f"unknown layer {layer!r}; choose from {', '.join(LAYERS + TRUTH_LAYERS)}")
    record = step_of(e, step)
    if record.damaged:
        raise RecordError(record.damaged)
    heads = heads_for(runner, e)  # an episode kept from an earlier server: its checkpoint's heads
    if record.maps is None or heads is None:
        raise RunnerError(f"episode {e.id} has no model maps: no model watched it")
    m = record.maps
    if layer in TRUTH_LAYERS:
        truth = episode_truth(e, m.semantic_w.shape[-1], runner.config.task.success_radius)
        return Response(png_bytes(upscale(truth_rgb(layer, truth, heads), 4)), media_type="image/png")
    layers = map_layers(m.maps, heads, world_names=tuple(lm.noun_phrase for lm in e.task.world.landmarks))
    if layer not in layers:
        raise RunnerError(f"episode {e.id}'s model records no map for layer {layer!r}")
    return Response(png_bytes(upscale(layers[layer].rgb, 4)), media_type="image/png")


@router.post("/api/ground", response_model=GroundResponse, responses=responses(400, 404, 409, 422, 503),
             summary="Ground another instruction on an episode's semantic map at a step, without flying")
def ground(request: GroundRequest, runner: TheRunner) -> GroundResponse:
    episode = episode_or_404(runner, request.episode_id)
    g: Grounding = runner.call(Ground(request.episode_id, request.instruction, request.step), COMMAND_TIMEOUT)
    heads = runner.models[episode.checkpoint].heads
    relevance = positive_probability(g.relevance_w, heads.grounding_w, heads.grounding_b) \
        if heads.grounding_trained else None
    goal = positive_probability(g.goal_w, heads.goal_w, heads.goal_b) if heads.goal_trained else None
    i = g.instruction
    return GroundResponse(episode_id=g.episode_id, step=g.step, instruction=i.text,
                          typed_instruction=request.instruction, landmark=i.noun_phrase,
                          side=i.side, goal_x=i.goal_x, goal_y=i.goal_y, v=g.v, omega=g.omega,
                          stop_probability=g.stop_probability, seconds=g.seconds,
                          relevance_probability=None if relevance is None else np.round(relevance, 4).tolist(),
                          goal_probability=None if goal is None else np.round(goal, 4).tolist())
