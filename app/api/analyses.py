"""The routes of an evaluation's analysis (`app.jobs.analysis`, `gsmn.analysis.slices`): slices, confusion matrices
and the versus table as JSON, the episodes behind any number, and the shipped evaluations (imported into the record
the first time they are asked for). Included with the job routes, when the server has a job manager."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query
from pydantic import Field

from app.api.deps import Jobs
from app.api.jobs import EpisodeModel, EvaluationId, EvaluationModel, episode_model, evaluation_model
from app.api.schema import Id, Strict, Text, responses
from app.live.commands import RunnerError
from gsmn.analysis.slices import ATTRIBUTES, CONFUSIONS

router = APIRouter()
Where = Annotated[list[Text], Query(max_length=4, description="attribute:value, e.g. landmark:tank (at most 4; "
                                     f"attributes: {', '.join(ATTRIBUTES)})")]


class ShippedRequest(Strict):
    key: Text = Field(..., min_length=1, max_length=200, description="a shipped evaluation's key, as "
                      "GET /api/shipped-evaluations lists them (e.g. table2/no-percept/dev)")


@router.get("/api/evaluations/{evaluation_id:int}/slices", responses=responses(404, 422, 503),
            summary="Success per slice, confusion matrices, and against another evaluation slice by slice")
def slices(evaluation_id: EvaluationId, jobs: Jobs,
           versus: Annotated[Id | None, Query(description="another evaluation of the same environments: fixed and "
                                               "broken episodes per slice, sign test")] = None) -> dict:
    return jobs.analyses.analysis(evaluation_id, versus)


@router.get("/api/evaluations/{evaluation_id:int}/slices/episodes", response_model=list[EpisodeModel],
            responses=responses(404, 422, 503), summary="The episodes behind a number of the analysis")
def slice_episodes(evaluation_id: EvaluationId, jobs: Jobs, where: Where = [],  # noqa: B006 - FastAPI's idiom
                   matrix: Annotated[str | None, Query(description=f"a confusion matrix: {', '.join(CONFUSIONS)}")]
                   = None, asked: Annotated[Text | None, Query(max_length=200)] = None,
                   read: Annotated[Text | None, Query(max_length=200)] = None,
                   ambiguous: bool | None = None,
                   versus: Annotated[Id | None, Query(description="a number of the versus table: only the "
                                                      "environments both evaluations flew")] = None
                   ) -> list[EpisodeModel]:
    criteria = {}
    for item in where:
        attribute, sep, value = item.partition(":")
        if not sep:
            raise RunnerError(f"where: expected attribute:value, got {item!r}")
        criteria[attribute] = value
    cell = None
    if matrix is not None or asked is not None or read is not None:
        if matrix is None or asked is None or read is None:
            raise RunnerError("a confusion cell needs matrix, asked and read")
        cell = (matrix, asked, read)
    return [episode_model(e) for e in jobs.analyses.episodes(evaluation_id, criteria, cell, ambiguous, versus)]


@router.get("/api/shipped-evaluations", responses=responses(503),
            summary="The evaluations shipped with the checkpoints (Table 1's and Table 2's), and their record ids")
def shipped(jobs: Jobs) -> list[dict]:
    return jobs.analyses.shipped()


@router.post("/api/shipped-evaluations/import", response_model=EvaluationModel, status_code=201,
             responses=responses(400, 404, 422, 503), summary="A shipped evaluation in the record (imported once)")
def import_shipped(request: ShippedRequest, jobs: Jobs) -> EvaluationModel:
    return evaluation_model(jobs, jobs.analyses.import_shipped(request.key))
