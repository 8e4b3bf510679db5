"""Exports of a kept episode (app.render.export): the self-contained HTML page opened from disk in headless Chromium
with no server running plays the episode (its camera and maps step with the slider); the GIF has one frame per step;
from the API and from `gsmn export` on the data folder after the server has stopped."""

from __future__ import annotations

import io
import subprocess
import sys
import time

import browser_support
import httpx
import pytest
from PIL import Image

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def flown(tmp_path_factory, untrained_checkpoint):
    """A data folder holding one finished episode of the untrained model (tiny preset), and that episode as the API
    gave it while the server ran, with its exports from the API."""
    from app.server import Dashboard
    from gsmn.config import preset, with_overrides

    folder = untrained_checkpoint
    data = tmp_path_factory.mktemp("data")
    d = Dashboard(with_overrides(preset("tiny"), {"task.horizon": "25"}), checkpoint=folder, port=0, api_port=0,
                  checkpoints_root=tmp_path_factory.mktemp("empty"), data_dir=data)
    try:
        with httpx.Client(base_url=d.urls.api, timeout=120) as c:
            episode_id = c.post("/api/episodes", json={"env_id": 70}).json()["id"]
            deadline = time.monotonic() + 120
            while (e := c.get(f"/api/episodes/{episode_id}").json())["status"] in ("queued", "running"):
                assert time.monotonic() < deadline
                time.sleep(0.1)
            exports = {fmt: c.get(f"/api/episodes/{episode_id}/export", params={"format": fmt})
                       for fmt in ("html", "gif", "mp4")}
            missing = c.get("/api/episodes/999/export")
    finally:
        d.close()
    return {"data": data, "episode": e, "exports": exports, "missing": missing}


def test_the_api_exports_html_a_gif_and_an_mp4_of_every_step(flown, tmp_path):
    e, exports = flown["episode"], flown["exports"]
    html, gif = exports["html"], exports["gif"]
    assert html.status_code == 200 and html.headers["content-type"].startswith("text/html")
    assert f'filename="episode-{e["id"]}.html"' in html.headers["content-disposition"]
    assert e["instruction"] in html.text and "http://" not in html.text.split("<script>")[1]  # nothing fetched
    assert gif.status_code == 200 and gif.headers["content-type"] == "image/gif"
    image = Image.open(io.BytesIO(gif.content))
    assert image.n_frames == e["steps"]
    # the MP4 (its encoder ships with the main install): a frame per step, as the GIF
    mp4 = exports["mp4"]
    assert mp4.status_code == 200 and mp4.headers["content-type"] == "video/mp4", mp4.text[:300]
    import imageio.v2 as imageio

    path = tmp_path / "episode.mp4"
    path.write_bytes(mp4.content)
    with imageio.get_reader(path, "ffmpeg") as video:
        assert sum(1 for _ in video) == e["steps"]
    assert flown["missing"].status_code == 404


@pytest.mark.browser
def test_the_command_line_exports_from_the_data_folder_and_the_page_plays_offline(flown, tmp_path):
    e = flown["episode"]
    out = tmp_path / "episode.html"
    done = subprocess.run([sys.executable, "-m", "gsmn.cli", "export", str(e["id"]), "--data-dir", str(flown["data"]),
                           "--format", "html", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert f"{e['steps']} steps" in done.stdout
    gif = tmp_path / "episode.gif"
    done = subprocess.run([sys.executable, "-m", "gsmn.cli", "export", str(e["id"]), "--data-dir", str(flown["data"]),
                           "--format", "gif", "--out", str(gif)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert Image.open(gif).n_frames == e["steps"]
    gone = subprocess.run([sys.executable, "-m", "gsmn.cli", "export", "999", "--data-dir", str(flown["data"])],
                          capture_output=True, text=True, timeout=300)
    assert gone.returncode == 1 and "no episode 999" in gone.stderr

    with browser_support.chromium() as browser:  # no server runs: the dashboard was closed above
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        requests = []
        page.on("request", lambda r: requests.append(r.url))
        page.goto(out.as_uri())

        def state():
            return page.evaluate("""() => ({step: +document.body.dataset.step,
                camera: document.getElementById('camera').src,
                goal: (document.querySelector('img[data-layer=goal]') || {}).src,
                loaded: [...document.images].every(i => !i.src || (i.complete && i.naturalWidth > 0)),
                title: document.getElementById('title').textContent,
                result: document.getElementById('result').textContent})""")

        first = state()
        assert first["step"] == 0 and first["camera"].startswith("data:image/jpeg") and first["loaded"]
        assert first["goal"].startswith("data:image/png") and e["instruction"] in first["title"]
        assert first["result"].startswith(("Success", "Failure"))
        page.locator("#slider").fill(str(e["steps"] - 1))  # the slider to the last step
        last = state()
        assert last["step"] == e["steps"] - 1 and last["camera"] != first["camera"] and last["goal"] != first["goal"]
        assert page.get_by_text(f"Step {e['steps'] - 1} of {e['steps'] - 1}").is_visible()
        page.locator("#slider").fill("0")
        page.get_by_role("button", name="Play").click()  # plays on by itself
        page.wait_for_function("() => +document.body.dataset.step >= 3", timeout=10_000)
        assert all(u.startswith(("file:", "data:")) for u in requests), requests
