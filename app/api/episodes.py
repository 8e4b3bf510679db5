"""The HTTP API (FastAPI; OpenAPI docs at /docs): start episodes, read their results and per-step data, and
ground counterfactual instructions on an episode's semantic map at any step.

It posts the same runner commands as the page (`app.live.runner`), so both share one behaviour. Handlers are plain
`def`s: FastAPI runs them on its thread pool, where waiting for the runner blocks nobody else. Every error
answers with a JSON body {"detail": "<what was wrong>"}: 404 for unknown episodes, 409 when the request does not
fit the state (no model loaded, no map yet, the queue full), 422 for bad input (an instruction that cannot be
understood, env_id < 0, NaN, missing checkpoint; `app.api.schema` says what every input may be), 503 when the simulator
does not answer in time; 401, 403 and 421 from the access checks (`app.api.access`). The OpenAPI schema lists each route's.
"""

from __future__ import annotations

import logging
from concurrent.futures import TimeoutError as FutureTimeout
from typing import Annotated, Literal

import numpy as np
from fastapi import FastAPI, Path, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, Response
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from app.api.schema import ACCESS, EnvId, Id, Strict, Text, path_id, plain_errors, responses, safe_text
from app.jobs.db import RecordError
from app.live.commands import MAX_ENV_ID, CancelEpisode, Ground, Grounding, NotFound, RunnerError, StartEpisode
from app.live.recording import Episode, EpisodeResult
from app.live.runner import Runner
from app.render.colors import png_bytes, upscale
from app.render.layers import LAYERS, map_layers
from app.render.truth import TRUTH_LAYERS, episode_truth, step_figures, truth_rgb, went_wrong
from gsmn.model.heads import positive_probability

log = logging.getLogger("gsmn.dashboard")
COMMAND_TIMEOUT = 60.0


MAX_STEP = 100_000  # more than any horizon
EpisodeId = Annotated[int, path_id("episode")]
Step = Annotated[int, Path(ge=0, le=MAX_STEP, description="the step, from 0")]


# -- request and response models -----------------------------------------------------------------------------
class EpisodeRequest(Strict):
    env_id: EnvId = Field(..., description=f"environment id, 0 to {MAX_ENV_ID} (id % 100: 0-69 train, 70-84 test, "
                          "85-99 dev)", examples=[70])
    instruction: Text | None = Field(None, max_length=500, description="free text, e.g. 'go to the left side of "
                                     "the barrel'; omitted: the environment's own instruction")
    checkpoint: Text | None = Field(
        None, min_length=1, max_length=1000, description="a checkpoint name under checkpoints/ or a "
                                    "folder; omitted: the default checkpoint")
    policy: Literal["model", "mirror", "expert"] = Field(
        "model", description="who flies: the model; the model as a test-time mirror ensemble (it also flies the "
        "mirror image of each step and the two actions are averaged; the maps are the unmirrored copy's); or the "
        "expert (with the model watching, when one is loaded)")


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


class Health(BaseModel):
    status: Literal["ok"]
    model_loaded: bool
    checkpoint_message: str
    live_episode: int | None
    episodes: int
    viewer_url: str | None


# -- the app --------------------------------------------------------------------------------------------------
def _result(r: EpisodeResult | None) -> ResultModel | None:
    return ResultModel(**r.__dict__) if r is not None else None


def summary(e: Episode) -> EpisodeSummary:
    i = e.task.instruction
    return EpisodeSummary(id=e.id, status=e.status, env_id=e.env_id, split=e.task.world.split,
                          instruction=i.text, typed_instruction=e.typed, landmark=i.noun_phrase, side=i.side,
                          goal_x=i.goal_x, goal_y=i.goal_y,
                          policy=e.policy, system=e.system, checkpoint=e.checkpoint, steps=len(e.steps),
                          horizon=e.horizon, steps_per_second=e.steps_per_second(), result=_result(e.result),
                          error=e.error, created=e.created)


def make_api(runner: Runner, viewer_url: str | None = None, jobs=None, keeper=None) -> FastAPI:
    """The API around `runner`; with `jobs` (app.jobs.manager.JobManager) also evaluations and fine-tuning runs; with
    `keeper` (app.jobs.kept.EpisodeKeeper) every episode kept in the record: searched, pinned, exported."""
    app = FastAPI(title="GSMN dashboard API", version="1.0",
                  description="Fly instructions with GSMN (Blukis et al., RSS 2018) on the MuJoCo quadcopter, read "
                              "episodes step by step, and ground counterfactual instructions on a semantic map "
                              "already built. Evaluate checkpoints, browse failures with their attribution, and "
                              "fine-tune with DAggerFM in separate processes. The browser view runs on the viser "
                              "port.", responses=responses(*ACCESS))

    @app.exception_handler(StarletteHTTPException)
    def http_error(request: Request, e: StarletteHTTPException) -> JSONResponse:
        """Starlette's own 404 and 405; a 405's Allow names every method the path takes (Starlette names only
        those of the first route that matches it)."""
        headers = dict(e.headers or {})
        if e.status_code == 405:
            headers["Allow"] = ", ".join(allowed_methods(app, request.url.path))
        return JSONResponse({"detail": str(e.detail)}, status_code=e.status_code, headers=headers)

    @app.exception_handler(RunnerError)
    def runner_error(request: Request, e: RunnerError) -> JSONResponse:
        return JSONResponse({"detail": str(e)}, status_code=e.status)

    @app.exception_handler(FutureTimeout)
    def timeout(request: Request, e: FutureTimeout) -> JSONResponse:
        return JSONResponse({"detail": "the simulator did not answer in time; try again"}, status_code=503)

    @app.exception_handler(RequestValidationError)
    def invalid(request: Request, e: RequestValidationError) -> JSONResponse:
        parts = []
        for err in e.errors():
            where = ".".join(str(x) for x in err.get("loc", ()) if x not in ("body", "path", "query"))
            parts.append(f"{where}: {err.get('msg')}" if where else str(err.get("msg")))
        return JSONResponse({"detail": safe_text("; ".join(parts) or "invalid request"),
                             "errors": plain_errors(e.errors())}, status_code=422)

    if jobs is not None:
        from app.api.jobs import add_job_routes

        add_job_routes(app, jobs, runner)

    def episode_or_404(episode_id: int) -> Episode:
        episode = runner.episodes.get(episode_id)
        if episode is None:
            raise NotFound(runner.episodes.missing(episode_id))
        return episode

    @app.get("/api/health", response_model=Health, summary="Is the server up, and is a model loaded")
    def health() -> Health:
        live = runner.live
        return Health(status="ok", model_loaded=runner.has_model, checkpoint_message=runner.checkpoint_message,
                      live_episode=live.id if live else None, episodes=len(runner.episodes), viewer_url=viewer_url)

    @app.get("/api/checkpoints", response_model=list[CheckpointModel], summary="Checkpoints the server can fly")
    def checkpoints() -> list[CheckpointModel]:
        return [CheckpointModel(**c.__dict__) for c in runner.checkpoint_list()]

    @app.post("/api/episodes", response_model=EpisodeCreated, status_code=201,
              responses=responses(400, 409, 422, 503), summary="Queue an episode; it flies after those before it")
    def create_episode(request: EpisodeRequest) -> EpisodeCreated:
        e = runner.call(StartEpisode(request.env_id, request.instruction, request.policy, request.checkpoint),
                        COMMAND_TIMEOUT)
        return EpisodeCreated(id=e.id, status=e.status, env_id=e.env_id, instruction=e.instruction,
                              typed_instruction=e.typed, policy=e.policy)

    if keeper is not None:
        from app.api.kept import add_kept_routes

        add_kept_routes(app, runner, keeper, summary)
    else:
        @app.get("/api/episodes", response_model=list[EpisodeSummary], summary="Episodes kept in memory, oldest "
                 "first")
        def list_episodes() -> list[EpisodeSummary]:
            return [summary(e) for e in runner.episodes.all()]

    @app.get("/api/episodes/{episode_id}", response_model=EpisodeSummary, responses=responses(404, 422),
             summary="Status, steps and result")
    def get_episode(episode_id: EpisodeId) -> EpisodeSummary:
        e = episode_or_404(episode_id)
        if keeper is None:
            return summary(e)
        row = keeper.db.kept(e.id)  # what the record holds of it: never more than that is said to be kept
        return summary(e).model_copy(update={
            "pinned": bool(row["pinned"]) if row else False, "bytes": int(row["bytes"]) if row else None,
            "kept_steps": int(row["steps"]) if row else 0, "keeping": keeper.behind(e.id)})

    @app.delete("/api/episodes/{episode_id}", response_model=EpisodeSummary,
                responses=responses(404, 409, 422, 503), summary="Cancel an episode: drop it from the queue, or end "
                "it if it is flying")
    def cancel_episode(episode_id: EpisodeId) -> EpisodeSummary:
        return summary(runner.call(CancelEpisode(episode_id), COMMAND_TIMEOUT))

    @app.get("/api/episodes/{episode_id}/steps", response_model=StepsResponse,
             responses=responses(404, 422),
             summary="Per-step poses and actions (all recorded steps; complete once finished)")
    def get_steps(episode_id: EpisodeId) -> StepsResponse:
        e = episode_or_404(episode_id)
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

    def step_of(e: Episode, step: int):
        if not 0 <= step < len(e.steps):
            raise RunnerError(f"step {step} is not recorded: episode {e.id} has {len(e.steps)} steps")
        return e.steps[step]

    @app.get("/api/episodes/{episode_id}/steps/{step}/camera.jpg", response_class=Response,
             responses={200: {"content": {"image/jpeg": {}}}, **responses(404, 422)},
             summary="The camera image at a step")
    def get_camera(episode_id: EpisodeId, step: Step) -> Response:
        return Response(step_of(episode_or_404(episode_id), step).camera_jpeg, media_type="image/jpeg")

    @app.get("/api/episodes/{episode_id}/steps/{step}/maps/{layer}.png", response_class=Response,
             responses={200: {"content": {"image/png": {}}}, **responses(404, 422)},
             summary="A map layer at a step as PNG (semantic, relevance, goal, goal_robot, or another map of the "
                     "model's output record by its name, e.g. coverage_w; or the ground truth: truth_semantic, "
                     "truth_relevance, truth_goal), 4x nearest-neighbour")
    def get_map(episode_id: EpisodeId, step: Step, layer: Literal[LAYERS + TRUTH_LAYERS]) -> Response:
        e = episode_or_404(episode_id)
        if layer not in LAYERS + TRUTH_LAYERS:
            raise RunnerError(f"unknown layer {layer!r}; choose from {', '.join(LAYERS + TRUTH_LAYERS)}")
        record = step_of(e, step)
        if record.damaged:
            raise RecordError(record.damaged)
        from app.render.export import heads_for  # an episode kept from an earlier server: its checkpoint's heads

        heads = heads_for(runner, e)
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

    @app.post("/api/ground", response_model=GroundResponse, responses=responses(400, 404, 409, 422, 503),
              summary="Ground another instruction on an episode's semantic map at a step, without flying")
    def ground(request: GroundRequest) -> GroundResponse:
        episode = episode_or_404(request.episode_id)
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

    from app.api.comparisons import add_compare_routes

    add_compare_routes(app, runner)
    return app


def allowed_methods(app: FastAPI, path: str) -> list[str]:
    """The methods of every route whose path matches `path`."""
    methods: set[str] = set()
    for route in app.routes:
        regex, route_methods = getattr(route, "path_regex", None), getattr(route, "methods", None)
        if regex is not None and route_methods and regex.match(path):
            methods |= set(route_methods)
    return sorted(methods)
