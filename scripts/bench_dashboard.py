#!/usr/bin/env python
"""Benchmark the live dashboard with a browser page open (headless Chromium through Playwright).

Measures, in one process serving the page and the API:
- live steps per second of whole episodes while the page is open and drawing every frame it can;
- time from clicking Run in the page to the first streamed frame drawn there (the maps panel of the new
  episode's first step, which the page updates last);
- counterfactual grounding latency: the grounding itself (runner), the API round trip, and from clicking
  Ground in the page to the what-if maps drawn there;
- live steps per second of a comparison (two episodes stepping together in one simulator) beside a single
  episode's, alternating in the same run, the fork snapshots' memory per step, and how long a fork takes to fly
  its first step (at the last step of an episode, and at the step before a keyframe, where it replays the most).

Targets (issue 6): >= 10 live steps/s on 2 cores, first frame within 1 s, grounding within 50 ms.
With --screenshots DIR it also writes dashboard_live.png (mid-episode) and dashboard_counterfactual.png.

    python scripts/bench_dashboard.py                      # tiny preset, untrained checkpoint unless one exists
    python scripts/bench_dashboard.py --preset paper --runs 5 --json out/bench_dashboard.json
    python scripts/bench_dashboard.py --preset paper --shadow-method baked --runs 5   # baked shadows (issue 80)
"""

from __future__ import annotations

import argparse
import dataclasses
import http.client
import json
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

from app.browser import CHROMIUM_ARGS, dismiss_notifications, field

os.environ.setdefault("MUJOCO_GL", "egl")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


CLICK_TO_FRAME = """async (label) => {
    const old = document.querySelector('.gsmn-maps')?.dataset.episode ?? '';
    const button = [...document.querySelectorAll('button')].find(b => b.innerText.trim() === label);
    const t0 = performance.now();
    button.click();
    return await new Promise((resolve) => {
        const tick = () => {
            const m = document.querySelector('.gsmn-maps');
            if (m && m.dataset.episode && m.dataset.episode !== old && m.dataset.step !== '') {
                resolve(performance.now() - t0);
            } else { setTimeout(tick, 2); }
        };
        tick();
    });
}"""

CLICK_TO_WHATIF = """async () => {
    const button = [...document.querySelectorAll('button')].find(b => b.innerText.trim() === 'Ground');
    const t0 = performance.now();
    button.click();
    return await new Promise((resolve) => {
        const tick = () => {
            const m = document.querySelector('.gsmn-maps');
            if (m && m.dataset.counterfactual === '1') { resolve(performance.now() - t0); }
            else { setTimeout(tick, 2); }
        };
        tick();
    });
}"""

COUNT_FRAMES = """() => {
    window.__frames = 0;
    window.__camera = 0;  // camera images received (the camera panel's src changing)
    let last = '', image = '';
    const target = document.querySelector('.gsmn-maps').parentElement;
    new MutationObserver(() => {
        const m = document.querySelector('.gsmn-maps');
        const key = m ? m.dataset.episode + '/' + m.dataset.step : '';
        if (key !== last) { last = key; window.__frames += 1; }
    }).observe(target, {childList: true, subtree: true});
    const camera = document.querySelector('img.gsmn-camera').closest('.mantine-Paper-root, div').parentElement;
    new MutationObserver(() => {
        const img = document.querySelector('img.gsmn-camera');
        if (img && img.src !== image) { image = img.src; window.__camera += 1; }
    }).observe(camera, {childList: true, subtree: true, attributes: true});
}"""





def wait(condition, timeout: float = 300.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise TimeoutError("benchmark step timed out")
        time.sleep(0.05)


def summary(values: list[float]) -> str:
    if not values:
        return "n/a"
    return (f"median {statistics.median(values):.1f}, min {min(values):.1f}, max {max(values):.1f} "
            f"(n = {len(values)})")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--preset", default="tiny", choices=("tiny", "paper"))
    ap.add_argument("--shadow-method", default=None, choices=("mujoco", "baked"),
                    help="camera.shadow_method (default: the preset's)")
    ap.add_argument("--checkpoint", default=None, help="GSMN checkpoint (default: checkpoints/gsmn if it exists, "
                    "else an untrained one biased to fly)")
    ap.add_argument("--env-id", type=int, default=70)
    ap.add_argument("--runs", type=int, default=3, help="Run clicks (first-frame latency) and whole live episodes")
    ap.add_argument("--groundings", type=int, default=30, help="API grounding requests")
    ap.add_argument("--chromium", default=os.environ.get("GSMN_CHROMIUM") or shutil.which("chromium"))
    ap.add_argument("--screenshots", default=None, help="folder for dashboard_live.png and "
                    "dashboard_counterfactual.png")
    ap.add_argument("--json", default=None, help="write the figures here")
    a = ap.parse_args()

    from playwright.sync_api import sync_playwright

    from app.live.commands import Ground, SetSpeed, StartEpisode
    from app.live.fixtures import make_untrained_checkpoint
    from app.server import CHECKPOINTS_ROOT, Dashboard
    from gsmn.config import preset

    checkpoint = a.checkpoint
    note = ""
    if checkpoint is None and (CHECKPOINTS_ROOT / "gsmn" / "meta.json").is_file():
        checkpoint = str(CHECKPOINTS_ROOT / "gsmn")
    if checkpoint is None:
        checkpoint = str(make_untrained_checkpoint(Path(tempfile.mkdtemp()) / "gsmn", a.preset))
        note = " (untrained, biased to fly: no trained checkpoint yet)"
    print(f"checkpoint: {checkpoint}{note}; preset {a.preset}, shadows {a.shadow_method or 'as the preset'}; "
          f"{os.cpu_count()} CPU cores; "
          f"load average {os.getloadavg()[0]:.1f} at start", flush=True)

    config = preset(a.preset)
    if a.shadow_method:
        config = dataclasses.replace(config, camera=dataclasses.replace(config.camera, shadow_method=a.shadow_method))
    dashboard = Dashboard(config, checkpoint=checkpoint, port=0, api_port=0, env_id=a.env_id,
                          data_dir=tempfile.mkdtemp(prefix="gsmn-bench-"))
    runner, figures = dashboard.runner, {}
    try:
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=a.chromium, args=CHROMIUM_ARGS)
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            page.set_default_timeout(120_000)
            page.goto(dashboard.urls.page)
            page.get_by_role("button", name="Run", exact=True).wait_for()
            page.wait_for_timeout(3000)  # let the scene arrive
            dismiss_notifications(page)

            # 1. Run -> first frame, and whole live episodes with the page open
            first_frame_ms, steps_per_second, page_fps, drawn, camera_fps = [], [], [], [], []
            for _ in range(a.runs):
                before = {e.id for e in runner.episodes.all()}
                first_frame_ms.append(page.evaluate(CLICK_TO_FRAME, "Run"))
                episode = next(e for e in runner.episodes.all() if e.id not in before)
                page.evaluate(COUNT_FRAMES)
                frames0, t0 = dashboard.viewer.frames_drawn, time.perf_counter()
                wait(lambda episode=episode: not episode.live)
                seconds = time.perf_counter() - t0
                steps_per_second.append(episode.steps_per_second() or 0.0)
                page_fps.append(page.evaluate("() => window.__frames") / seconds)
                camera_fps.append(page.evaluate("() => window.__camera") / seconds)
                drawn.append((dashboard.viewer.frames_drawn - frames0) / max(len(episode.steps), 1))
                page.wait_for_timeout(500)
            server_ms = [1000 * x for x in dashboard.viewer.click_to_frame[-a.runs:]]
            figures["first_frame_ms"] = first_frame_ms
            figures["first_frame_server_ms"] = server_ms
            figures["live_steps_per_second"] = steps_per_second
            figures["page_steps_shown_per_second"] = page_fps
            figures["page_camera_images_per_second"] = camera_fps
            figures["fraction_of_steps_drawn"] = drawn
            print(f"Run -> first frame in the page (ms): {summary(first_frame_ms)}", flush=True)
            print(f"  of which the server (click callback to frame sent): {summary(server_ms)}", flush=True)
            print(f"live steps/s with the page open:     {summary(steps_per_second)}", flush=True)
            print(f"steps shown per second in the page:  {summary(page_fps)}", flush=True)
            print(f"camera images per second in the page: {summary(camera_fps)}", flush=True)
            print(f"steps drawn by the viewer:           {summary([100 * d for d in drawn])} %", flush=True)
            viewer = dashboard.viewer
            figures["viewer_ms_per_frame"] = 1000 * viewer.render_seconds / max(viewer.frames_drawn, 1)
            print(f"viewer's drawing per frame drawn:    {figures['viewer_ms_per_frame']:.1f} ms", flush=True)

            # 2. counterfactual grounding latency: runner, API round trip, page click -> what-if maps drawn
            last = runner.episodes.all()[-1]
            texts = [f"go to the {side} side of the {lm.noun_phrase}" for lm in last.task.world.landmarks
                     for side in ("left", "right", "front", "back")]
            compute_ms, api_ms = [], []
            # one kept-alive connection, as a client that asks many questions would use
            host, port = dashboard.urls.api.removeprefix("http://").rsplit(":", 1)
            connection = http.client.HTTPConnection(host, int(port), timeout=30)
            for i in range(a.groundings):
                body = json.dumps({"episode_id": last.id, "instruction": texts[i % len(texts)],
                                   "step": i % len(last.steps)})
                t0 = time.perf_counter()
                connection.request("POST", "/api/ground", body, {"Content-Type": "application/json"})
                response = connection.getresponse()
                answer = json.loads(response.read())
                api_ms.append(1000 * (time.perf_counter() - t0))
                if response.status != 200:
                    raise RuntimeError(f"/api/ground answered {response.status}: {answer}")
                compute_ms.append(1000 * answer["seconds"])
            connection.close()
            for i in range(5):  # the runner's own call, without HTTP and JSON
                g = runner.call(Ground(last.id, texts[(i + 1) % len(texts)]))
                compute_ms.append(1000 * g.seconds)
            page_ms = []
            for i in range(min(5, len(texts))):
                whatif = field(page, "What if")
                whatif.fill(texts[(3 * i + 1) % len(texts)])
                whatif.press("Enter")
                page.wait_for_timeout(300)
                page.get_by_role("button", name="Clear", exact=True).click()
                page.wait_for_timeout(500)
                page_ms.append(page.evaluate(CLICK_TO_WHATIF))
            whatif_server_ms = [1000 * x for x in dashboard.viewer.whatif_to_frame[-len(page_ms):]]
            figures.update(grounding_compute_ms=compute_ms, grounding_api_ms=api_ms, grounding_page_ms=page_ms,
                           grounding_page_server_ms=whatif_server_ms)
            print(f"grounding itself (ms):               {summary(compute_ms)}", flush=True)
            print(f"grounding over the API (ms):         {summary(api_ms)}", flush=True)
            print(f"click Ground -> what-if maps (ms):   {summary(page_ms)}", flush=True)
            print(f"  of which the server (click callback to maps sent): {summary(whatif_server_ms)}", flush=True)

            # 3. a comparison (two episodes stepping together in the runner's one simulator) beside a single
            # episode, both flown to the end here with the page open; then a fork at the last step
            figures.update(compare_and_fork(runner, a.env_id, a.runs))

            if a.screenshots:
                take_screenshots(page, dashboard, Path(a.screenshots), runner, SetSpeed, StartEpisode,
                                 expert=bool(note))
            browser.close()
    finally:
        dashboard.close()
    figures["load_average_end"] = os.getloadavg()[0]
    print(f"load average at the end: {figures['load_average_end']:.1f}")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps(figures, indent=1))
    return 0


def compare_and_fork(runner, env_id: int, runs: int) -> dict:
    """Live steps per second of a single episode and of a comparison (timeline steps: one step of each episode),
    alternating, in one run; the snapshots' memory per step; the time a fork takes to fly its first step."""
    from app.live.commands import StartEpisode
    from app.live.compare import ForkEpisode, PolicySpec, StartComparison
    from gsmn.task.fork import KEYFRAME_EVERY

    single, pair, pair_total, snapshot_bytes, fork_ms = [], [], [], [], []
    for _ in range(max(runs, 1)):
        e = runner.call(StartEpisode(env_id, None, "model"))
        wait(lambda e=e: not e.live)
        single.append(e.steps_per_second() or 0.0)
        snapshot_bytes.append(e.snapshots.nbytes() / max(len(e.steps), 1))
        c = runner.call(StartComparison(env_id, None, [PolicySpec("model"), PolicySpec("expert")]))
        wait(lambda c=c: not any(x.live for x in c.episodes))
        first = min(x.first_frame for x in c.episodes)
        last = max(x.finished for x in c.episodes)
        rounds = max(len(x.steps) for x in c.episodes) - 1
        pair.append(rounds / max(last - first, 1e-9))
        pair_total.append((sum(len(x.steps) for x in c.episodes) - 2) / max(last - first, 1e-9))
        for t in (len(e.steps) - 1, KEYFRAME_EVERY - 1):  # the last step; the most replayed
            t0 = time.perf_counter()
            fork = runner.call(ForkEpisode(e.id, t))
            wait(lambda fork=fork, t=t: len(fork.steps) > t)
            fork_ms.append(1000 * (time.perf_counter() - t0))
            wait(lambda fork=fork: not fork.live)
    print(f"live steps/s, a single episode:      {summary(single)}", flush=True)
    print(f"live steps/s, a comparison (timeline steps, both drones): {summary(pair)}", flush=True)
    print(f"  episode steps/s over both:         {summary(pair_total)}", flush=True)
    print(f"fork snapshots per step (kB):        {summary([b / 1000 for b in snapshot_bytes])}", flush=True)
    print(f"fork -> its first step flown (ms):   {summary(fork_ms)}", flush=True)
    return {"single_steps_per_second": single, "comparison_steps_per_second": pair,
            "comparison_episode_steps_per_second": pair_total, "snapshot_bytes_per_step": snapshot_bytes,
            "fork_first_step_ms": fork_ms}


def take_screenshots(page, dashboard, out: Path, runner, SetSpeed, StartEpisode, expert: bool = False) -> None:
    """Mid-episode (the model flying at real time, or with `expert` the expert flying while the model watches;
    relevance and goal on the ground, colours over each frame's range), then a counterfactual on the finished
    episode's map."""
    out.mkdir(parents=True, exist_ok=True)
    page.set_viewport_size({"width": 1500, "height": 1000})
    field(page, "Relevance map").click()
    field(page, "Colour range").click()  # each frame's own range: an untrained model's maps are nearly flat
    page.get_by_role("option", name="frame").click()
    page.get_by_role("button", name="Clear", exact=True).click()
    runner.call(SetSpeed(5.0))
    try:
        if expert:  # an untrained model does not fly anywhere worth showing
            field(page, "Policy").click()
            page.get_by_role("option", name="Expert (oracle)").click()
        page.get_by_role("button", name="Run", exact=True).click()
        wait(lambda: runner.live is not None)
        episode = runner.live
        wait(lambda: len(episode.steps) >= 45 or not episode.live)  # mid-flight, or a model that stopped early
        page.wait_for_timeout(400)
        dismiss_notifications(page)
        page.mouse.move(700, 880)
        page.screenshot(path=str(out / "dashboard_live.png"))
        print(f"wrote {out / 'dashboard_live.png'}")
    finally:
        runner.call(SetSpeed(None))
    wait(lambda: not episode.live)
    page.wait_for_timeout(1000)
    whatif = field(page, "What if")
    text = episode.task.instruction.text
    other = next(lm.noun_phrase for lm in episode.task.world.landmarks
                 if lm.noun_phrase != episode.task.instruction.noun_phrase)
    whatif.fill(text.replace(episode.task.instruction.noun_phrase, other))
    whatif.press("Enter")
    page.get_by_role("button", name="Ground", exact=True).click()
    page.wait_for_function("() => document.querySelector('.gsmn-maps')?.dataset.counterfactual === '1'")
    page.wait_for_timeout(800)
    dismiss_notifications(page)
    page.screenshot(path=str(out / "dashboard_counterfactual.png"))
    print(f"wrote {out / 'dashboard_counterfactual.png'}")


if __name__ == "__main__":
    sys.exit(main())
