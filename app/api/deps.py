"""What the route handlers are given besides the request: the runner, the job manager, the episode keeper and the
page's URL, as FastAPI dependencies that read them from `request.app.state` (where `app.api.app.make_api` puts
them), so a route module holds no state of its own and adds no parameter to the OpenAPI schema.

Handlers are plain `def`s: FastAPI runs them on its thread pool, where waiting for the runner (`COMMAND_TIMEOUT`)
blocks nobody else. These dependencies only read an attribute, so they are `async` and run on the event loop.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from app.jobs.kept import EpisodeKeeper
from app.jobs.manager import JobManager
from app.live.commands import NotFound
from app.live.recording import Episode
from app.live.runner import Runner

COMMAND_TIMEOUT = 60.0  # s, for the runner to answer a command


async def _runner(request: Request) -> Runner:
    return request.app.state.runner


async def _jobs(request: Request) -> JobManager:
    return request.app.state.jobs


async def _keeper(request: Request) -> EpisodeKeeper | None:
    return request.app.state.keeper


async def _viewer_url(request: Request) -> str | None:
    return request.app.state.viewer_url


TheRunner = Annotated[Runner, Depends(_runner)]
Jobs = Annotated[JobManager, Depends(_jobs)]  # only on routes added when there is one
Keeper = Annotated[EpisodeKeeper, Depends(_keeper)]  # only on routes added when there is one
MaybeKeeper = Annotated[EpisodeKeeper | None, Depends(_keeper)]
ViewerUrl = Annotated[str | None, Depends(_viewer_url)]


def episode_or_404(runner: Runner, episode_id: int) -> Episode:
    episode = runner.episodes.get(episode_id)
    if episode is None:
        raise NotFound(runner.episodes.missing(episode_id))
    return episode
