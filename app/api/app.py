"""The HTTP API (FastAPI; OpenAPI docs at /docs): `make_api` builds the app around the runner (and, when the server
has them, the job manager and the episode keeper), with its error answers and the routers of `app.api`.

Every error answers with a JSON body {"detail": "<what was wrong>"}: 404 for unknown episodes, 409 when the request
does not fit the state (no model loaded, no map yet, the queue full), 422 for bad input (an instruction that cannot
be understood, env_id < 0, NaN, missing checkpoint; `app.api.schema` says what every input may be), 503 when the
simulator does not answer in time; 401, 403 and 421 from the access checks (`app.api.access`). The OpenAPI schema
lists each route's.

The routes, in the order they are matched: evaluations and runs (`app.api.jobs`, with a job manager) and their
analyses (`app.api.analyses`), health,
checkpoints and queueing an episode (`app.api.episodes`), the episode list (`app.api.kept` with a keeper, else
in memory), an episode and its steps (`app.api.episodes`), camera images, maps and grounding (`app.api.maps`),
comparisons and forks (`app.api.comparisons`). Each handler reads what it needs from `app.state` (`app.api.deps`).
"""

from __future__ import annotations

from concurrent.futures import TimeoutError as FutureTimeout

from fastapi import APIRouter, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from app.api import analyses, comparisons, episodes, kept, maps
from app.api import jobs as job_routes
from app.api.schema import ACCESS, plain_errors, responses, safe_text
from app.jobs.kept import EpisodeKeeper
from app.jobs.manager import JobManager
from app.live.commands import RunnerError
from app.live.runner import Runner

DESCRIPTION = ("Fly instructions with GSMN (Blukis et al., RSS 2018) on the MuJoCo quadcopter, read episodes step by "
               "step, and ground counterfactual instructions on a semantic map already built. Evaluate checkpoints, "
               "browse failures with their attribution, and fine-tune with DAggerFM in separate processes. The "
               "browser view runs on the viser port.")
HTTP_METHODS = ("CONNECT", "DELETE", "GET", "HEAD", "OPTIONS", "PATCH", "POST", "PUT", "TRACE")  # sorted


def make_api(runner: Runner, viewer_url: str | None = None, jobs: JobManager | None = None,
             keeper: EpisodeKeeper | None = None) -> FastAPI:
    """The API around `runner`; with `jobs` (app.jobs.manager.JobManager) also evaluations and fine-tuning runs; with
    `keeper` (app.jobs.kept.EpisodeKeeper) every episode kept in the record: searched, pinned, exported."""
    app = FastAPI(title="GSMN dashboard API", version="1.0", description=DESCRIPTION, responses=responses(*ACCESS))
    app.state.runner, app.state.viewer_url, app.state.jobs, app.state.keeper = runner, viewer_url, jobs, keeper
    app.add_exception_handler(StarletteHTTPException, http_error)
    app.add_exception_handler(RunnerError, runner_error)
    app.add_exception_handler(FutureTimeout, timeout)
    app.add_exception_handler(RequestValidationError, invalid)
    for router in routers(jobs is not None, keeper is not None):
        app.include_router(router)
    return app


def routers(with_jobs: bool, with_keeper: bool) -> list[APIRouter]:
    """The routers in the order their routes are matched (and listed in the OpenAPI schema)."""
    return [*([job_routes.router, analyses.router] if with_jobs else []), episodes.router,
            kept.router if with_keeper else episodes.in_memory, episodes.episode_router, maps.router,
            comparisons.router]


# -- error answers ----------------------------------------------------------------------------------------------
def http_error(request: Request, e: StarletteHTTPException) -> JSONResponse:
    """Starlette's own 404 and 405; a 405's Allow names every method the path takes (Starlette names only
    those of the first route that matches it)."""
    headers = dict(e.headers or {})
    if e.status_code == 405:
        headers["Allow"] = ", ".join(allowed_methods(request.app, request.url.path))
    return JSONResponse({"detail": str(e.detail)}, status_code=e.status_code, headers=headers)


def runner_error(request: Request, e: RunnerError) -> JSONResponse:
    return JSONResponse({"detail": str(e)}, status_code=e.status)


def timeout(request: Request, e: FutureTimeout) -> JSONResponse:
    return JSONResponse({"detail": "the simulator did not answer in time; try again"}, status_code=503)


def invalid(request: Request, e: RequestValidationError) -> JSONResponse:
    parts = []
    for err in e.errors():
        where = ".".join(str(x) for x in err.get("loc", ()) if x not in ("body", "path", "query"))
        parts.append(f"{where}: {err.get('msg')}" if where else str(err.get("msg")))
    return JSONResponse({"detail": safe_text("; ".join(parts) or "invalid request"),
                         "errors": plain_errors(e.errors())}, status_code=422)


def allowed_methods(app: FastAPI, path: str) -> list[str]:
    """The methods of every route whose path matches `path`. Asked of each route by Starlette's `matches`, which
    routes included from a router answer too (FastAPI >= 0.165 keeps them as one route per router)."""
    methods = []
    for method in HTTP_METHODS:
        scope = {"type": "http", "path": path, "root_path": "", "method": method, "headers": []}
        if any(route.matches(scope)[0] == Match.FULL for route in app.routes):
            methods.append(method)
    return methods
