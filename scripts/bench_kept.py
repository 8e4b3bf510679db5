"""What a kept episode costs on disk (app.jobs.kept): flies episodes in a throw-away data folder with the dashboard's
runner and keeper, and prints the stored bytes per episode and per step (camera JPEG, quantised maps, numbers),
the growth of the SQLite file, how long the writer took per step, and an export's sizes.

    python scripts/bench_kept.py --preset paper --checkpoint checkpoints/gsmn --env-ids 73 70 71
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from app.jobs.db import Database  # noqa: E402
from app.jobs.kept import EpisodeKeeper  # noqa: E402
from app.jobs.kept_store import KeptStore  # noqa: E402
from app.live.commands import StartEpisode  # noqa: E402
from app.live.runner import Runner  # noqa: E402
from app.render.export import export_episode, heads_for  # noqa: E402
from gsmn.config import preset  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="paper")
    p.add_argument("--checkpoint", default="checkpoints/gsmn")
    p.add_argument("--env-ids", type=int, nargs="+", default=[73, 70, 71])
    args = p.parse_args()
    import torch

    torch.set_num_threads(1)
    config = preset(args.preset)
    with tempfile.TemporaryDirectory() as folder:
        db = Database(Path(folder) / "gsmn.sqlite")
        store = KeptStore(db, config)
        runner = Runner(config, Path(args.checkpoint).resolve(), require_checkpoint=True, episodes=store).start()
        keeper = EpisodeKeeper(store, 10**12, live=lambda: runner.live.id if runner.live else None)
        runner.listeners.append(keeper)
        written = []
        original = keeper._flush_steps

        def timed(steps):
            n = sum(len(v) for v in steps.values())
            t0 = time.perf_counter()
            original(steps)
            if n:
                written.append((n, time.perf_counter() - t0))

        keeper._flush_steps = timed
        file0 = Path(folder, "gsmn.sqlite").stat().st_size
        try:
            for env_id in args.env_ids:
                episode = runner.call(StartEpisode(env_id, None, "model", None))
                while episode.live:
                    time.sleep(0.1)
            keeper.flush()
            rows = db._all("SELECT episode_id, count(*) AS n, sum(length(camera)) AS cam, sum(length(maps)) AS maps, "
                           "sum(length(data)) AS data FROM kept_steps GROUP BY episode_id")
            total_steps = 0
            for r in rows:
                row = db.kept(r["episode_id"])
                total_steps += r["n"]
                print(f"episode {r['episode_id']} (env {row['env_id']}): {r['n']} steps, {row['bytes'] / 1e6:.2f} MB = "
                      f"{row['bytes'] / r['n'] / 1e3:.1f} kB a step (camera {r['cam'] / r['n'] / 1e3:.1f} kB, maps "
                      f"{r['maps'] / r['n'] / 1e3:.1f} kB, numbers {r['data'] / r['n'] / 1e3:.2f} kB)")
            db._db.execute("PRAGMA wal_checkpoint(TRUNCATE)")
            grown = Path(folder, "gsmn.sqlite").stat().st_size - file0
            print(f"record file grew {grown / 1e6:.2f} MB for {total_steps} steps ({db.kept_bytes() / 1e6:.2f} MB "
                  f"stored)")
            n, seconds = sum(w[0] for w in written), sum(w[1] for w in written)
            print(f"writer: {seconds / max(n, 1) * 1e3:.2f} ms a step ({len(written)} transactions for {n} steps), "
                  "on its own thread")
            episode = store.load(rows[0]["episode_id"])
            t0 = time.perf_counter()
            loaded = store.load(rows[0]["episode_id"])
            print(f"read back: {len(loaded.steps)} steps in {time.perf_counter() - t0:.2f} s")
            for fmt in ("html", "gif"):
                t0 = time.perf_counter()
                data = export_episode(episode, fmt, heads_for(runner, episode))
                print(f"export {fmt}: {len(data) / 1e6:.2f} MB in {time.perf_counter() - t0:.1f} s")
        finally:
            runner.close()
            keeper.close()
            db.close()


if __name__ == "__main__":
    main()
