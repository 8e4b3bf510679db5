"""`gsmn serve`: one process with the runner, the viser page and the FastAPI API (uvicorn on a thread).

Every browser tab that connects gets its own page (`Tab`: a viewer, its jobs, presenter and episodes views, built
on viser's client-level handles) and loses it when it goes; the runner, the jobs and the record are shared.

Both servers bind to loopback by default, and both check every request's Host, Origin and (when there is one)
token (`app.api.access`): bound beyond loopback they need a token, printed at start-up in the page's URL. viser moves
to the next free port silently when its port is taken, so the URLs are read back from the bound sockets; the API
does the same (and says so). Port 0 picks any free port (the tests use it).
"""

from __future__ import annotations

import contextlib
import io
import logging
import socket
import threading
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

import uvicorn
import viser

from app.api.access import (
    Access,
    AccessMiddleware,
    guard_viser,
    install_viser_guard,
    is_loopback,
    machine_addresses,
    resolve_token,
    unguard_viser,
    url,
)
from app.api.app import make_api
from app.jobs.kept import DEFAULT_LIMIT_MB, EpisodeKeeper
from app.jobs.kept_store import KeptStore
from app.jobs.manager import JobManager
from app.live.commands import Conflict, RunnerError, ShowEnv
from app.live.runner import Runner
from app.page.episodes_view import EpisodesView
from app.page.jobs_view import JobsView
from app.page.presenter import Presenter
from app.page.viewer import Viewer, configure_server
from gsmn.config import RunConfig

log = logging.getLogger("gsmn.dashboard")
DEFAULT_CHECKPOINT = "gsmn"  # checkpoints/gsmn
DEFAULT_DATA_DIR = "data/dashboard"
CHECKPOINTS_ROOT = Path(__file__).resolve().parents[1] / "checkpoints"


def _url(host: str, port: int) -> str:
    shown = {"0.0.0.0": "127.0.0.1", "": "127.0.0.1", "::": "::1"}.get(host, host)
    return url(shown, port)


def bind_socket(host: str, port: int, tries: int = 20) -> tuple[socket.socket, bool]:
    """A listening TCP socket on `port`, or on the next free one (like viser). Returns (socket, moved)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    last: OSError | None = None
    for attempt in range(tries if port else 1):
        # proto IPPROTO_TCP, not 0: asyncio sets TCP_NODELAY only on sockets that say they are TCP, and without
        # it every kept-alive response waits about 40 ms for a delayed ACK (Nagle)
        sock = socket.socket(family, socket.SOCK_STREAM, socket.IPPROTO_TCP)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port + attempt if port else 0))
        except OSError as e:
            sock.close()
            last = e
            continue
        sock.listen(128)
        sock.set_inheritable(True)
        return sock, attempt > 0
    raise OSError(f"no free port for the API from {port} to {port + tries - 1} on {host}: {last}")


class ApiServer:
    """uvicorn serving a FastAPI app on a daemon thread, on a socket bound beforehand."""

    def __init__(self, app, host: str, port: int, bound: tuple[socket.socket, bool] | None = None):
        self.socket, self.moved = bound or bind_socket(host, port)
        self.host, self.port = host, self.socket.getsockname()[1]
        config = uvicorn.Config(app, log_level="warning", access_log=False, timeout_graceful_shutdown=2)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.socket]}, name="gsmn-api",
                                       daemon=True)
        self.thread.start()

    def wait_started(self, timeout: float = 30.0) -> None:
        import time

        deadline = time.monotonic() + timeout
        while not self.server.started and self.thread.is_alive() and time.monotonic() < deadline:
            time.sleep(0.02)
        if not self.server.started:
            raise RuntimeError("the API server did not start")

    @property
    def url(self) -> str:
        return _url(self.host, self.port)

    def close(self) -> None:
        self.server.should_exit = True
        self.thread.join(timeout=5)
        self.socket.close()


@dataclass
class Urls:
    page: str  # with ?token=... when there is a token
    api: str
    api_moved: bool
    token: str | None = None
    notes: tuple[str, ...] = ()  # what `gsmn serve` prints besides: a warning off loopback, the real addresses


class Dashboard:
    """The whole dashboard in this process. `checkpoint` None means the default (checkpoints/gsmn, optional);
    a path given explicitly must load. Evaluations and fine-tuning runs are recorded under `data_dir`."""

    def __init__(self, config: RunConfig, checkpoint: str | Path | None = None, host: str = "127.0.0.1",
                 port: int = 8080, api_port: int = 8000, env_id: int = 70,
                 checkpoints_root: str | Path = CHECKPOINTS_ROOT, max_episodes: int = 16, torch_threads: int = 1,
                 data_dir: str | Path = DEFAULT_DATA_DIR, max_runs: int = 1, max_evaluations: int = 1,
                 token: str | None = None, keep_mb: float | None = None):
        """`keep_mb`: the retention limit of kept episodes (app.jobs.kept; None: its default). `token`: the token
        requests must carry ("" makes one; None: $GSMN_TOKEN, else one only when `host`
        is not loopback)."""
        from gsmn.model.runtime import set_torch_threads

        # One thread: the runner does one small step at a time, and on a busy machine two threads spin
        # against each other (measured: an inference step went from 8 ms to 200-500 ms under load).
        set_torch_threads(torch_threads)
        # the record first: a damaged or empty one is refused (naming it) before the simulator starts
        self.jobs = JobManager(data_dir, config, self.resolve_checkpoint, max_runs=max_runs,
                               max_evaluations=max_evaluations, checkpoints_root=checkpoints_root)
        self.kept = KeptStore(self.jobs.db, config, max_episodes)  # every episode flown, in the record
        try:
            self.runner = Runner(config, checkpoint if checkpoint is not None else DEFAULT_CHECKPOINT,
                                 require_checkpoint=checkpoint is not None, checkpoints_root=checkpoints_root,
                                 max_episodes=max_episodes, episodes=self.kept).start()
        except BaseException:
            self.jobs.close()
            raise
        self.keeper = EpisodeKeeper(self.kept, int((DEFAULT_LIMIT_MB if keep_mb is None else keep_mb) * 1e6),
                                    live=lambda: self.runner.live.id if self.runner.live else None)
        self.runner.listeners.append(self.keeper)
        self.runner.checkpoints.extra = self.jobs.checkpoints
        token = resolve_token(token, host)
        api_socket = bind_socket(host, api_port)  # first: the checks of both servers need both ports
        install_viser_guard()
        with contextlib.redirect_stdout(io.StringIO()):  # viser prints a banner even when not verbose
            self.viser = viser.ViserServer(host=host, port=port, verbose=False, label="GSMN dashboard")
        self.access = Access.for_bind(host, (self.viser.get_port(), api_socket[0].getsockname()[1]), token)
        guard_viser(self.viser.get_port(), self.access)
        configure_server(self.viser)
        self.env_id = env_id
        self.tabs: dict[int, Tab] = {}  # by viser client id, in the order they connected
        self._tabs_lock = threading.Lock()
        self._gone: set[int] = set()  # clients that left before their tab was built
        self._closed = False
        self.viser.on_client_disconnect(self._disconnect)  # first: a client that comes and goes at once is seen go
        self.viser.on_client_connect(self._connect)
        page_url = _url(host, self.viser.get_port())
        app = make_api(self.runner, page_url, self.jobs, self.keeper)
        app.add_middleware(AccessMiddleware, access=self.access)
        self.api = ApiServer(app, host, api_port, bound=api_socket)
        self.api.wait_started()
        self.urls = Urls(page_url + (f"/?token={token}" if token else ""), self.api.url, self.api.moved, token,
                         _notes(host, self.viser.get_port(), self.api.port, token))
        self.runner.call(ShowEnv(env_id))

    # -- tabs -------------------------------------------------------------------------------------------------
    def _connect(self, client: viser.ClientHandle) -> None:
        """A tab opened (viser's thread pool): build its page."""
        try:
            tab = Tab(client, self)
        except Exception:  # noqa: BLE001 - a tab that cannot be built must not take the server down
            log.error("building the page of client %d failed:\n%s", client.client_id, traceback.format_exc())
            with self._tabs_lock:
                self._gone.discard(client.client_id)
            return
        with self._tabs_lock:
            gone = client.client_id in self._gone or self._closed
            self._gone.discard(client.client_id)
            if not gone:
                self.tabs[client.client_id] = tab
        if gone:
            tab.close()

    def _disconnect(self, client: viser.ClientHandle) -> None:
        with self._tabs_lock:
            tab = self.tabs.pop(client.client_id, None)
            if tab is None:
                self._gone.add(client.client_id)
        if tab is not None:
            tab.close()

    def tab(self, wait: float = 30.0) -> Tab:
        """The newest open tab's page (for tests and scripts), waiting up to `wait` s for one to connect."""
        deadline = time.monotonic() + wait
        while True:
            with self._tabs_lock:
                if self.tabs:
                    return next(reversed(self.tabs.values()))
            if time.monotonic() >= deadline:
                raise LookupError("no browser tab is open on the dashboard")
            time.sleep(0.05)

    @property
    def viewer(self) -> Viewer:
        return self.tab().viewer

    @property
    def presenter(self) -> Presenter:
        return self.tab().presenter

    @property
    def episodes_view(self) -> EpisodesView:
        return self.tab().episodes_view

    @property
    def jobs_view(self) -> JobsView:
        return self.tab().jobs_view

    def resolve_checkpoint(self, ref: str | None) -> Path:
        """A checkpoint name (under checkpoints/, or run-N) or folder; None: the default one."""
        if ref is None:
            if self.runner.default_model is None:
                raise Conflict(f"no default checkpoint: {self.runner.checkpoint_message} Name one.")
            return Path(self.runner.default_model)
        path = self.runner.checkpoints.path_of(ref)
        try:
            if not (path / "meta.json").is_file():
                raise RunnerError(f"no checkpoint at {path}")
            return path.resolve()
        except OSError as e:
            raise RunnerError(f"no checkpoint at {path}: {e.strerror or e}") from e

    def close(self) -> None:
        """Stop serving. Running evaluations and runs go on; the next `gsmn serve` re-attaches to them."""
        self.api.close()
        unguard_viser(self.viser.get_port())
        with self._tabs_lock:
            self._closed = True  # a tab still being built closes itself when done
            tabs, self.tabs = list(self.tabs.values()), {}
        for tab in tabs:
            tab.close()
        self.runner.close()
        self.keeper.close()
        self.jobs.close()
        with contextlib.redirect_stdout(io.StringIO()):
            self.viser.stop()


class Tab:
    """One browser tab's page: its viewer (controls, scene, timeline), its Failures and Fine-tune tabs, presenter
    mode and Episodes tab, all on the client's own viser handles."""

    def __init__(self, client: viser.ClientHandle, dashboard: Dashboard):
        self.client = client
        started = time.perf_counter()
        self.viewer = Viewer(client, dashboard.runner, dashboard.env_id)
        try:
            self.jobs_view = JobsView(self.viewer, dashboard.jobs)
            self.presenter = Presenter(self.viewer)
            self.episodes_view = EpisodesView(self.viewer, dashboard.keeper, self.presenter)
        except BaseException:
            self.close()  # the parts built so far
            raise
        self.built_seconds = time.perf_counter() - started  # the server's share of opening a tab
        log.info("tab %d built in %.2f s", client.client_id, self.built_seconds)

    def close(self) -> None:
        for part in (getattr(self, "episodes_view", None), getattr(self, "presenter", None),
                     getattr(self, "jobs_view", None), self.viewer):
            if part is not None:
                part.close()


def _notes(host: str, page_port: int, api_port: int, token: str | None) -> tuple[str, ...]:
    """What `gsmn serve` says besides the URLs: off loopback, a warning and the addresses it really answers on."""
    notes = []
    if not is_loopback(host):
        notes.append(f"warning: bound to {host}, beyond loopback: anyone who can reach this machine and has the "
                     "token can fly, evaluate and fine-tune here")
        query = f"/?token={token}" if token else ""
        for address in machine_addresses(host):
            notes.append(f"  page {url(address, page_port, query)}   API {url(address, api_port, '/api')}")
    if token:
        notes.append(f"token: {token}  (API requests: header 'Authorization: Bearer {token}')")
    return tuple(notes)
