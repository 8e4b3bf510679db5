"""`gsmn serve`: the dashboard's subcommand, registered with the `gsmn` command line through the entry-point group
`gsmn.commands` (pyproject.toml), so that the library (gsmn/) never imports the app."""

from __future__ import annotations

import argparse
import sys

from gsmn.cli import add_config_arguments, config_from_args


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add `serve` to the `gsmn` subcommands."""
    p = subparsers.add_parser("serve", help="serve the dashboard: the browser view (viser) and the HTTP API (FastAPI)")
    p.add_argument("--checkpoint", default=None, help="GSMN checkpoint folder to fly (default: checkpoints/gsmn "
                   "when it exists; without one the expert flies and the page says so)")
    p.add_argument("--host", default="127.0.0.1", help="address to bind both servers (default: loopback only; "
                   "beyond it every request needs the token printed at start-up)")
    p.add_argument("--token", nargs="?", const="", default=None, help="require this token (alone: a fresh one, "
                   "printed) of every API request and the page's WebSocket, also on loopback (default: $GSMN_TOKEN; "
                   "required and made up when --host is not loopback)")
    p.add_argument("--port", type=int, default=8080, help="browser view port (the next free one is used if taken)")
    p.add_argument("--api-port", type=int, default=8000, help="HTTP API port (the next free one is used if taken)")
    p.add_argument("--env-id", type=int, default=70, help="environment shown first (default: the first test one)")
    p.add_argument("--data-dir", default="data/dashboard", help="evaluations, fine-tuning runs and their records "
                   "(SQLite database gsmn.sqlite and one folder per job); kept across restarts")
    p.add_argument("--max-runs", type=int, default=1, help="fine-tuning runs at a time; more are refused")
    p.add_argument("--max-evaluations", type=int, default=1, help="evaluations at a time; more are refused")
    p.add_argument("--keep-mb", type=float, default=None, help="disk space for the episodes kept (every episode "
                   "flown in the page or over the API); past it the oldest unpinned ones are removed (default: 2000)")
    add_config_arguments(p)
    p.set_defaults(func=cmd_serve)


def cmd_serve(args: argparse.Namespace) -> int:
    import signal
    import threading
    import time

    from app.server import Dashboard

    # A shell starts a background job (`gsmn serve &` in a script, a CI step) with SIGINT ignored, and Python keeps
    # it ignored: "Ctrl+C to stop" and `kill -INT PID` would do nothing, and a supervisor's graceful stop would
    # wait out its timeout. A server is stopped by signals, so it takes SIGINT back (the other commands keep a
    # background job's protection from the terminal's Ctrl-C).
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)

    config = config_from_args(args)
    try:
        dashboard = Dashboard(config, checkpoint=args.checkpoint, host=args.host, port=args.port,
                              api_port=args.api_port, env_id=args.env_id, data_dir=args.data_dir,
                              max_runs=args.max_runs, max_evaluations=args.max_evaluations, token=args.token,
                              keep_mb=args.keep_mb)
    except Exception as e:  # noqa: BLE001 - e.g. an explicit --checkpoint that does not load
        print(f"gsmn serve: error: {e}", file=sys.stderr)
        return 2
    try:  # from here on Ctrl-C, at any moment, closes the dashboard
        urls = dashboard.urls
        print(f"gsmn dashboard: {urls.page}  (Ctrl+C to stop)", flush=True)
        moved = f" (port {args.api_port} was taken)" if urls.api_moved else ""
        print(f"API: {urls.api}/api{moved}  OpenAPI docs: {urls.api}/docs", flush=True)
        for note in urls.notes:  # off loopback: a warning and the real addresses; the token
            print(note, flush=True)
        print(("model: " if dashboard.runner.has_model else "no model: ") + dashboard.runner.checkpoint_message,
              flush=True)
        print(f"data: {dashboard.jobs.describe()}", flush=True)
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        dashboard.close()
    return 0


def register_export(subparsers: argparse._SubParsersAction) -> None:
    """Add `export` to the `gsmn` subcommands."""
    p = subparsers.add_parser("export", help="export an episode the dashboard kept: a self-contained HTML page that "
                              "plays it back with no server, or a GIF/MP4 of the camera beside the maps")
    p.add_argument("episode_id", type=int, help="the episode's id (the page's episode list, GET /api/episodes)")
    p.add_argument("--data-dir", default="data/dashboard", help="the dashboard's data folder (gsmn serve --data-dir)")
    p.add_argument("--format", choices=("html", "gif", "mp4"), default="html")
    p.add_argument("--out", default=None, help="the file to write (default: episode-ID.FORMAT)")
    add_config_arguments(p)
    p.set_defaults(func=cmd_export)


def cmd_export(args: argparse.Namespace) -> int:
    from pathlib import Path

    from app.jobs.db import Database, RecordError
    from app.jobs.kept_store import KeptStore
    from app.render.export import export_episode, heads_for

    record = Path(args.data_dir) / "gsmn.sqlite"
    if not record.is_file():
        print(f"gsmn export: error: no dashboard record at {record} (give the folder of gsmn serve --data-dir)",
              file=sys.stderr)
        return 2
    try:
        db = Database(record)
    except (RecordError, RuntimeError) as e:
        print(f"gsmn export: error: {e}", file=sys.stderr)
        return 2
    try:
        store = KeptStore(db, config_from_args(args))
        episode = store.load(args.episode_id)
        if episode is None:
            print(f"gsmn export: error: {store.missing(args.episode_id)}", file=sys.stderr)
            return 1
        if not episode.steps:
            print(f"gsmn export: error: episode {args.episode_id} has no steps", file=sys.stderr)
            return 1

        class _NoModels:  # heads_for reads the episode's checkpoint folder when no runner holds its model
            models: dict = {}

        try:
            data = export_episode(episode, args.format, heads_for(_NoModels(), episode))
        except ValueError as e:
            print(f"gsmn export: error: {e}", file=sys.stderr)
            return 2
        out = Path(args.out or f"episode-{args.episode_id}.{args.format}")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(data)
        print(f"{out}: episode {episode.id}, {len(episode.steps)} steps, {len(data) / 1e6:.2f} MB")
        return 0
    finally:
        db.close()
