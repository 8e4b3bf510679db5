"""The routes of evaluations, their episodes and failure attribution, and DAggerFM fine-tuning runs
(`app.jobs.manager`). Errors answer {"detail": ...} as the rest of the API: 404 for unknown ids, 409 when a limit
is reached or there is nothing to cancel or resume, 413 for a file too large to import, 422 for bad input, 503 when
the record cannot be written (`app.api.schema` says what every input may be).

`app.api.app` includes `router` first, and only when the server has a job manager. Who flies a replay is
`app.jobs.results.replay_policy`, which the page asks too.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query, Response
from pydantic import BaseModel, Field

from app.api.deps import COMMAND_TIMEOUT, Jobs, TheRunner
from app.api.schema import EnvId, Id, Strict, Text, path_id, responses
from app.jobs.db import EpisodeRow, Evaluation, Run
from app.jobs.evaluation_export import FORMATS, export_evaluation, export_name, finite
from app.jobs.manager import CORES, MAX_IMPORT_BYTES, JobManager
from app.jobs.results import replay_intervention, replay_policy, rescue_of
from app.jobs.settings import MAX_ROLLOUTS, RUN_PRESETS, run_settings
from app.live.commands import NotFound, RunnerError, StartEpisode
from gsmn.attribution import STAGES

router = APIRouter()
SYSTEMS = Literal["gsmn", "gsmn-no-plan", "gs-fpv", "gs-fpv-mem", "oracle"]
STATUS = Literal["queued", "running", "finished", "failed", "cancelled"]
EvaluationId = Annotated[int, path_id("evaluation")]
Intervention = Literal["truth-semantic", "truth-relevance", "truth-goal"]
RunId = Annotated[int, path_id("run")]


class EvaluationRequest(Strict):
    checkpoint: Text | None = Field(
        None, min_length=1, max_length=1000, description="checkpoint name (under checkpoints/, or "
                                    "run-N for a fine-tuning run) or folder; omitted: the server's default")
    system: SYSTEMS | None = Field(None, description="omitted: the checkpoint's kind; 'oracle' flies the expert")
    split: Literal["train", "test", "dev"] | None = Field(None, description="evaluate on this split ...")
    episodes: int | None = Field(None, ge=1, le=5000, description="... its first this many environments")
    env_ids: list[EnvId] | None = Field(None, min_length=1, max_length=5000, description="or these environment ids")
    baseline_id: Id | None = Field(None, description="rerun the episodes of this evaluation (before/after); "
                                    "also the default environments")
    run_id: Id | None = Field(None, description="evaluate this finished fine-tuning run's checkpoint")
    workers: int = Field(1, ge=1, le=CORES, description="worker processes, at most this machine's cores (one core "
                         "each; 1 leaves the live view its share)")
    mirror_ensemble: bool = Field(False, description="fly the model as a test-time mirror ensemble (it also flies "
                                  "the mirror image of each step and the two actions are averaged; not in the paper)")
    intervention: Intervention | None = Field(None, description="fly a GSMN with this truth map in place of its own "
                                              "from the first step (gsmn eval --intervene; docs/model.md)")


class RescueRequest(Strict):
    intervention: Intervention = Field(..., description="the truth map the failures fly with: perfect perception "
                                       "(truth-semantic), grounding (truth-relevance) or goal (truth-goal)")


class ImportRequest(Strict):
    path: Text = Field(..., min_length=1, max_length=1000, description="a `gsmn eval --json` file inside the data "
                       f"folder (relative: to it), a regular file of at most {MAX_IMPORT_BYTES // 2**20} MiB")
    record_dir: Text | None = Field(None, min_length=1, max_length=1000, description="its `--record` folder, for "
                                    "failure attribution, inside the data folder too")


class ReplayRequest(Strict):
    env_id: EnvId


class EvaluationModel(BaseModel):
    id: int
    status: STATUS
    label: str
    system: str
    checkpoint: str | None
    env_ids: list[int]
    baseline_id: int | None
    run_id: int | None
    source: Literal["dashboard", "import"]
    mirror_ensemble: bool = Field(description="flown as a test-time mirror ensemble")
    intervention: str | None = Field(None, description="the truth map it flew with (gsmn eval --intervene); null: "
                                     "the model's own maps")
    done: int = Field(description="episodes finished")
    total: int
    fraction: float
    summary: dict | None = Field(description="success %, landmark success %, mean and median distance (m); "
                                 "'pruned': the same on unambiguous instructions; of the episodes done so far")
    stages: dict[str, int] = Field(description="failures per attribution stage")
    regions: dict[str, int] = Field(description="failures that flew through the success region without a STOP there "
                                    "('entered'), that never entered it ('never'), recorded without it ('unknown')")
    error: str | None
    created: float
    started: float | None
    finished: float | None


class EpisodeModel(BaseModel):
    evaluation_id: int
    position: int
    env_id: int
    instruction: str
    landmark: str
    side: str
    ambiguous: bool
    success: bool
    landmark_success: bool
    goal_distance: float
    steps: int
    stopped: bool
    final_x: float
    final_y: float
    stage: str | None = Field(description="attribution of a failure: perception, grounding, goal or control; for "
                              "a model with an untrained head the merged stage (gsmn.attribution.STAGES)")
    attribution: dict | None = Field(description="the evidence (gsmn.attribution.Attribution)")
    region_steps: list[int] | None = Field(None, description="the steps at which a STOP would have succeeded "
                                           "(inside the success region); null: not recorded")
    region_stop_p: float | None = Field(None, description="the model's highest P(stop) at those steps, when recorded")


class Replayed(BaseModel):
    episode_id: int
    env_id: int
    policy: str
    checkpoint: str | None


_PAPER = RUN_PRESETS["paper"]


class RunRequest(Strict):
    preset: Literal[tuple(RUN_PRESETS)] = Field(
        "tiny", description=f"tiny: a minute or two on a 2-core machine; small: tens of minutes; paper: the original's "
        f"settings, whose {_PAPER.iterations} x {_PAPER.rollouts_per_iteration} rollouts are more than the "
        f"{MAX_ROLLOUTS} the dashboard launches: give fewer iterations")
    iterations: int | None = Field(None, ge=1, le=MAX_ROLLOUTS, description=f"iterations x N_D at most "
                                   f"{MAX_ROLLOUTS}")
    rollouts_per_iteration: int | None = Field(None, ge=1, le=MAX_ROLLOUTS, description="N_D")
    dataset_size: int | None = Field(None, ge=1, le=100000, description="M")
    beta0: float | None = Field(None, ge=0, le=1)
    learning_rate: float | None = Field(None, gt=0, le=1)
    horizon: int | None = Field(None, ge=1, le=1000, description="steps per rollout")
    batch_size: int | None = Field(None, ge=1, le=64)
    workers: int | None = Field(None, ge=1, le=CORES, description="rollout worker processes, at most this machine's "
                                "cores")
    threads: int | None = Field(None, ge=1, le=CORES, description="torch threads of the training, at most this "
                                "machine's cores")
    mirror: float | None = Field(None, ge=0, le=1, description="share of training episodes mirrored east-west "
                                 "(left and right swapped; not in the paper); omitted: the preset's, 0")
    expert_data: Text | None = Field(None, max_length=1000, description="an expert episode store (gsmn collect) "
                                     "to start the dataset from; omitted: collected in the data folder")
    checkpoint: Text | None = Field(
        None, min_length=1, max_length=1000, description="start from this checkpoint; omitted: the "
                                    "server's default")
    env_ids: list[EnvId] | None = Field(None, min_length=1, max_length=5000, description="roll out in these")
    evaluation_id: Id | None = Field(None, description="roll out in this evaluation's failures (when no "
                                      "env_ids); neither: the train split")


class RunModel(BaseModel):
    id: int
    status: STATUS
    settings: dict
    env_ids: list[int] | None
    source_evaluation_id: int | None
    init_checkpoint: str
    checkpoint: str | None = Field(description="the fine-tuned checkpoint, once finished (name: run-<id>)")
    progress: dict | None = Field(description="phase, iteration, iterations, fraction, text")
    metrics: list[dict] = Field(description="one record per finished iteration (losses, accuracies, beta)")
    error: str | None
    folder: str
    created: float
    started: float | None
    finished: float | None


def evaluation_model(jobs: JobManager, e: Evaluation) -> EvaluationModel:
    return EvaluationModel(id=e.id, status=e.status, label=e.label, system=e.system, checkpoint=e.checkpoint,
                           env_ids=e.env_ids, baseline_id=e.baseline_id, run_id=e.run_id, source=e.source,
                           mirror_ensemble=e.mirror_ensemble, intervention=e.intervention, done=e.done,
                           total=e.total,
                           fraction=e.done / max(1, e.total), summary=finite(e.summary),
                           stages=jobs.db.stage_counts(e.id), regions=jobs.db.region_counts(e.id), error=e.error,
                           created=e.created, started=e.started, finished=e.finished)


def episode_model(e: EpisodeRow) -> EpisodeModel:
    return EpisodeModel(**{k: finite(v) for k, v in e.__dict__.items() if k != "recording"})


def run_model(r: Run) -> RunModel:
    return RunModel(id=r.id, status=r.status, settings=r.settings, env_ids=r.env_ids,
                    source_evaluation_id=r.source_evaluation_id, init_checkpoint=r.init_checkpoint,
                    checkpoint=r.checkpoint if r.status == "finished" else None, progress=finite(r.progress),
                    metrics=finite(r.metrics), error=r.error, folder=r.folder, created=r.created, started=r.started,
                    finished=r.finished)


# -- evaluations ---------------------------------------------------------------------------------------------
@router.post("/api/evaluations", response_model=EvaluationModel, status_code=201,
             responses=responses(400, 404, 409, 422, 503),
             summary="Evaluate a checkpoint on a split or environments, in a separate process")
def create_evaluation(request: EvaluationRequest, jobs: Jobs) -> EvaluationModel:
    checkpoint = request.checkpoint
    if request.run_id is not None and checkpoint is None:
        run = jobs.run(request.run_id)
        if run.status != "finished":
            raise RunnerError(f"run {run.id} is {run.status}; only a finished run has a checkpoint")
        checkpoint = run.checkpoint
    e = jobs.start_evaluation(checkpoint, request.system, request.split, request.episodes, request.env_ids,
                              request.baseline_id, request.run_id, request.workers, request.mirror_ensemble,
                              request.intervention)
    return evaluation_model(jobs, e)


@router.post("/api/evaluations/{evaluation_id}/rescue", response_model=EvaluationModel, status_code=201,
             responses=responses(404, 409, 422, 503),
             summary="Fly an evaluation's failures again with a truth map intervention (a new evaluation)")
def rescue_failures(evaluation_id: EvaluationId, request: RescueRequest, jobs: Jobs) -> EvaluationModel:
    return evaluation_model(jobs, jobs.rescue_failures(evaluation_id, request.intervention))


@router.get("/api/evaluations/{evaluation_id}/rescue", responses=responses(404, 422),
            summary="How many of an evaluation's failures each truth map rescued, per attributed stage")
def rescue_table(evaluation_id: EvaluationId, jobs: Jobs) -> dict:
    return finite(rescue_of(jobs.db, jobs.evaluation(evaluation_id)))


@router.get("/api/evaluations", response_model=list[EvaluationModel], responses=responses(503),
            summary="Every evaluation recorded")
def list_evaluations(jobs: Jobs) -> list[EvaluationModel]:
    return [evaluation_model(jobs, e) for e in jobs.db.evaluations()]


@router.post("/api/evaluations/import", response_model=EvaluationModel, status_code=201,
             responses=responses(400, 403, 404, 413, 422, 503),
             summary="Record the results of `gsmn eval --json` (and its --record folder) as an evaluation")
def import_evaluation(request: ImportRequest, jobs: Jobs) -> EvaluationModel:
    return evaluation_model(jobs, jobs.import_evaluation(request.path, request.record_dir))


@router.get("/api/evaluations/{evaluation_id:int}", response_model=EvaluationModel,
            responses=responses(404, 422, 503),
            summary="Status, progress, summary so far and attribution counts")
def get_evaluation(evaluation_id: EvaluationId, jobs: Jobs) -> EvaluationModel:
    return evaluation_model(jobs, jobs.evaluation(evaluation_id))


@router.delete("/api/evaluations/{evaluation_id:int}", response_model=EvaluationModel,
               responses=responses(404, 409, 422, 503),
               summary="Cancel a running evaluation (its process group gets SIGTERM, then SIGKILL)")
def cancel_evaluation(evaluation_id: EvaluationId, jobs: Jobs) -> EvaluationModel:
    return evaluation_model(jobs, jobs.cancel_evaluation(evaluation_id))


@router.post("/api/evaluations/{evaluation_id:int}/resume", response_model=EvaluationModel,
             responses=responses(404, 409, 422, 503),
             summary="Fly the rest of a cancelled or failed evaluation, keeping the episodes it had finished")
def resume_evaluation(evaluation_id: EvaluationId, jobs: Jobs) -> EvaluationModel:
    return evaluation_model(jobs, jobs.resume_evaluation(evaluation_id))


@router.get("/api/evaluations/{evaluation_id:int}/episodes", response_model=list[EpisodeModel],
            responses=responses(404, 422, 503),
            summary="Its episodes in the order flown, with attribution; filters as in the failure browser")
def list_evaluation_episodes(evaluation_id: EvaluationId, jobs: Jobs, failed_only: bool = False,
                             landmark: Annotated[Text | None, Query(max_length=200)] = None,
                             side: Literal["left", "right", "front", "back"] | None = None,
                             ambiguous: bool | None = None,
                             stage: Literal[STAGES] | None = None,
                             entered_region: bool | None = None) -> list[EpisodeModel]:
    jobs.evaluation(evaluation_id)
    return [episode_model(e) for e in jobs.db.episodes(evaluation_id, failed_only, landmark, side, ambiguous,
                                                         stage, entered_region)]


@router.get("/api/evaluations/{evaluation_id:int}/export", response_class=Response,
            responses={200: {"content": {"text/csv": {}, "application/json": {}}}, **responses(404, 422, 503)},
            summary="Its results as a file: CSV, one row per episode naming its split and what flew it, or JSON, "
                    "the evaluation with its summary and episodes (an unfinished one says how many it holds)")
def export_evaluation_results(evaluation_id: EvaluationId, jobs: Jobs, format: Annotated[
        Literal["csv", "json"], Query(description="csv: for a spreadsheet; json: with the summary")] = "csv"
                              ) -> Response:
    e = jobs.evaluation(evaluation_id)
    return Response(export_evaluation(jobs.db, e, format), media_type=FORMATS[format],
                    headers={"Content-Disposition": f'attachment; filename="{export_name(e, format)}"'})


@router.post("/api/evaluations/{evaluation_id:int}/replay", response_model=Replayed, status_code=201,
             responses=responses(400, 404, 409, 422, 503),
             summary="Fly an episode of the evaluation again in the live view, with its maps")
def replay(evaluation_id: EvaluationId, request: ReplayRequest, jobs: Jobs, runner: TheRunner) -> Replayed:
    e = jobs.evaluation(evaluation_id)
    if jobs.db.episode(evaluation_id, request.env_id) is None:
        raise NotFound(f"evaluation {evaluation_id} has no episode in environment {request.env_id}")
    policy, checkpoint = replay_policy(e)
    episode = runner.call(StartEpisode(request.env_id, None, policy, checkpoint, intervention=replay_intervention(e)),
                          COMMAND_TIMEOUT)
    return Replayed(episode_id=episode.id, env_id=request.env_id, policy=policy, checkpoint=checkpoint)


@router.get("/api/evaluations/{before_id:int}/compare/{after_id:int}", responses=responses(404, 422, 503),
            summary="Before/after: the episodes two evaluations share, side by side")
def compare(before_id: EvaluationId, after_id: EvaluationId, jobs: Jobs) -> dict:
    return finite(jobs.compare(before_id, after_id))


# -- runs ----------------------------------------------------------------------------------------------------
@router.post("/api/runs", response_model=RunModel, status_code=201, responses=responses(400, 404, 409, 422, 503),
             summary="Launch DAggerFM fine-tuning from a checkpoint, in a separate process")
def create_run(request: RunRequest, jobs: Jobs) -> RunModel:
    fields = request.model_dump(exclude={"preset", "checkpoint", "env_ids", "evaluation_id"})
    settings = run_settings(request.preset, **fields)
    return run_model(jobs.start_run(settings, request.checkpoint, request.env_ids, request.evaluation_id))


@router.get("/api/runs", response_model=list[RunModel], responses=responses(503),
            summary="Every fine-tuning run recorded")
def list_runs(jobs: Jobs) -> list[RunModel]:
    return [run_model(r) for r in jobs.db.runs()]


@router.get("/api/runs/{run_id:int}", response_model=RunModel, responses=responses(404, 422, 503),
            summary="Status, progress, metrics so far, and the checkpoint when done")
def get_run(run_id: RunId, jobs: Jobs) -> RunModel:
    return run_model(jobs.run(run_id))


@router.delete("/api/runs/{run_id:int}", response_model=RunModel, responses=responses(404, 409, 422, 503),
               summary="Cancel a run (SIGTERM, then SIGKILL, to its process group); its folder stays")
def cancel_run(run_id: RunId, jobs: Jobs) -> RunModel:
    return run_model(jobs.cancel_run(run_id))


@router.post("/api/runs/{run_id:int}/resume", response_model=RunModel, responses=responses(404, 409, 422, 503),
             summary="Continue a cancelled or failed run from the iterations its folder saved")
def resume_run(run_id: RunId, jobs: Jobs) -> RunModel:
    return run_model(jobs.resume_run(run_id))
