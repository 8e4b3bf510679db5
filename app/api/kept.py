"""The routes of the episodes kept in the record (`app.jobs.kept`): search them, pin them, see and set the space
they may take, and export one (`app.render.export`).

`app.api.app` includes `router` only when the server has an episode keeper, between `app.api.episodes`' `router`
and `episode_router`: its `GET /api/episodes` then stands for the in-memory list.
"""

from __future__ import annotations

from typing import Annotated, Literal

from fastapi import APIRouter, Query
from fastapi.responses import Response
from pydantic import BaseModel, Field

from app.api.deps import Keeper, TheRunner
from app.api.models import EpisodeId, EpisodeSummary, Policy, summary
from app.api.schema import MAX_ID, Strict, Text, responses
from app.jobs.kept import OUTCOMES, EpisodeKeeper, row_summary, search
from app.live.commands import Conflict, NotFound, RunnerError
from app.render.export import MEDIA_TYPES, export_episode, heads_for

router = APIRouter()
MAX_TIME = 1e11  # unix seconds, year 5138


class Storage(BaseModel):
    episodes: int = Field(description="episodes kept in the record")
    pinned: int
    bytes: int = Field(description="what their steps take (camera JPEGs, quantised maps, numbers): what the "
                       "retention limit counts")
    limit_bytes: int = Field(description="past it (in `bytes`) the oldest unpinned episodes are removed")
    file_bytes: int = Field(description="the record's files on disk (gsmn.sqlite and its -wal and -shm, evaluations "
                            "and runs included): above `bytes` by SQLite's pages, rows and write-ahead log, which the "
                            "limit does not count")
    removed: list[int] = Field(description="episodes the limit removed since the server started, oldest first")


class StorageRequest(Strict):
    limit_mb: float = Field(..., ge=0.0, le=1e7, description="the retention limit in MB (10^6 bytes); 0 keeps "
                            "only the pinned episodes")


@router.get("/api/episodes", response_model=list[EpisodeSummary], responses=responses(422, 503),
            summary="Episodes flown in the page or over the API, kept in the record across restarts, searched")
def list_episodes(
        keeper: Keeper,
        env_id: Annotated[int | None, Query(ge=0, le=2**31 - 1, description="the environment")] = None,
        instruction: Annotated[Text | None, Query(max_length=500, description="a part of the instruction, any "
                                                  "case")] = None,
        policy: Annotated[Policy | None, Query(description="who flew")] = None,
        system: Annotated[Text | None, Query(max_length=100, description="what flew: the checkpoint's kind "
                                             "(gsmn, gsmn-no-plan) or oracle")] = None,
        checkpoint: Annotated[Text | None, Query(max_length=1000, description="the checkpoint that flew (or "
                                                 "watched the expert), as `checkpoint` in a summary")] = None,
        outcome: Annotated[Literal[OUTCOMES] | None, Query(
            description="success; failure (finished without success); cancelled; failed (an error, or the "
                        "server stopped while it flew); live (flying or queued)")] = None,
        pinned: Annotated[bool | None, Query(description="pinned only, or unpinned only")] = None,
        since: Annotated[float | None, Query(ge=0, le=MAX_TIME, description="started at or after (unix s)")] = None,
        until: Annotated[float | None, Query(ge=0, le=MAX_TIME, description="started at or before (unix s)")] = None,
        order: Annotated[Literal["newest", "oldest"], Query(description="by id")] = "newest",
        limit: Annotated[int, Query(ge=1, le=1000)] = 100,
        offset: Annotated[int, Query(ge=0, le=MAX_ID)] = 0) -> list[EpisodeSummary]:
    store = keeper.store
    keeper.flush()
    rows = search(keeper.db, env_id, instruction, policy, system, outcome, pinned, since, until, order == "newest",
                  limit, offset, checkpoint)
    out = []
    for row in rows:
        episode = store.get_in_memory(int(row["id"]))
        if episode is not None and episode.live:  # fresher than the record (its step count)
            out.append(summary(episode).model_copy(update={
                "pinned": bool(row["pinned"]), "bytes": int(row["bytes"]), "kept_steps": int(row["steps"]),
                "keeping": keeper.behind(episode.id)}))
        else:
            out.append(EpisodeSummary(**row_summary(row)))
    filtered = any(v is not None for v in (env_id, instruction, policy, system, checkpoint, pinned, since, until)) \
        or outcome not in (None, "live")
    if not filtered and offset == 0:  # queued episodes are not in the record until they fly
        kept = {e.id for e in out}
        queued = [summary(e) for e in store.all() if e.status == "queued" and e.id not in kept]
        out = (queued[::-1] + out if order == "newest" else out + queued)[:limit]
    return out


def kept_row(keeper: EpisodeKeeper, episode_id: int):
    keeper.flush()
    row = keeper.db.kept(episode_id)
    if row is None:
        episode = keeper.store.get_in_memory(episode_id)
        if episode is not None:
            raise Conflict(f"episode {episode_id} is {episode.status}: it is kept once it starts flying")
        raise NotFound(keeper.store.missing(episode_id))
    return row


def set_pin(keeper: EpisodeKeeper, episode_id: int, pinned: bool) -> EpisodeSummary:
    kept_row(keeper, episode_id)
    keeper.db.update_kept(episode_id, pinned=int(pinned))
    return EpisodeSummary(**row_summary(keeper.db.kept(episode_id)))


@router.put("/api/episodes/{episode_id}/pin", response_model=EpisodeSummary, responses=responses(404, 409, 422, 503),
            summary="Pin an episode: the retention limit never removes it")
def pin(episode_id: EpisodeId, keeper: Keeper) -> EpisodeSummary:
    return set_pin(keeper, episode_id, True)


@router.delete("/api/episodes/{episode_id}/pin", response_model=EpisodeSummary,
               responses=responses(404, 409, 422, 503), summary="Unpin an episode")
def unpin(episode_id: EpisodeId, keeper: Keeper) -> EpisodeSummary:
    return set_pin(keeper, episode_id, False)


def storage(keeper: EpisodeKeeper) -> Storage:
    keeper.flush()
    db = keeper.db
    counts = db.kept_counts()
    return Storage(episodes=counts["episodes"], pinned=counts["pinned"], bytes=db.kept_bytes(),
                   limit_bytes=keeper.limit_bytes, file_bytes=db.file_bytes(), removed=list(keeper.removed))


@router.get("/api/storage", response_model=Storage, responses=responses(503),
            summary="Space the kept episodes take, and the retention limit")
def get_storage(keeper: Keeper) -> Storage:
    return storage(keeper)


@router.put("/api/storage", response_model=Storage, responses=responses(400, 422, 503),
            summary="Set the retention limit; episodes past it are removed at once, oldest unpinned first")
def put_storage(request: StorageRequest, keeper: Keeper) -> Storage:
    keeper.set_limit(int(request.limit_mb * 1e6))
    return storage(keeper)


@router.get("/api/episodes/{episode_id}/export", response_class=Response,
            responses={200: {"content": {"text/html": {}, "image/gif": {}, "video/mp4": {}}},
                       **responses(404, 409, 422, 503)},
            summary="The episode as one self-contained HTML page that plays it back with no server, or as a GIF "
                    "or MP4 of the camera beside the maps with the step, instruction and result written on it")
def export(episode_id: EpisodeId, runner: TheRunner, keeper: Keeper, format: Annotated[Literal["html", "gif", "mp4"],
           Query(description="html: a page that plays back offline; gif or mp4: for slides")] = "html") -> Response:
    store = keeper.store
    episode = store.get(episode_id)
    if episode is None:
        raise NotFound(store.missing(episode_id))
    if not episode.steps:
        raise Conflict(f"episode {episode_id} has no steps yet")
    try:
        data = export_episode(episode, format, heads_for(runner, episode), runner.config)
    except ValueError as e:
        raise RunnerError(str(e)) from e
    name = f"episode-{episode_id}.{format}"
    return Response(data, media_type=MEDIA_TYPES[format],
                    headers={"Content-Disposition": f'attachment; filename="{name}"'})
