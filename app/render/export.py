"""An episode taken away from the dashboard: one self-contained HTML page that plays it back in any browser with no
server, or an animated GIF (or MP4, where ffmpeg is installed) of the camera beside the maps, for slides.

The HTML page is written here rather than with viser's scene serialiser (`ViserServer.get_scene_serializer`, whose
recording plays back only in viser's own client build, a folder of JavaScript served beside the file): a page
with the per-step images embedded (the camera JPEG and the map PNGs as data URIs) and a 60-line script (a slider,
play and pause) is one file that opens from disk, and it shows what a person reads in the dashboard's right
panel: the camera, the maps labelled in plain words, the flown path, the actions and the result.

Every frame of a GIF or MP4 is one step: the camera image, the semantic, relevance and goal maps, and a caption
with the step, the instruction and the result. `gsmn export` (app.cli) and `GET /api/episodes/{id}/export` both
call `export_episode`.

The semantic map is read as "which of this world's landmarks, or nothing" (`app.render.layers`, reading "world"),
with its legend: a person who did not see the dashboard reads the few landmarks the world has, not a mosaic of the
63 classes the head knows.
"""

from __future__ import annotations

import base64
import html
import io
import json
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw, ImageFont

from app.live.models import MapHeads
from app.live.recording import FINISHED, Episode
from app.render.colors import NOTHING, OTHER_RGB, UNSEEN_RGB, decode_image, name_palette, png_bytes, upscale
from app.render.layers import map_layers

FORMATS = ("html", "gif", "mp4")
MEDIA_TYPES = {"html": "text/html; charset=utf-8", "gif": "image/gif", "mp4": "video/mp4"}
STEPS_PER_SECOND = 5  # the simulator's rate: an export plays in real time
# the maps in plain words (the presenter's labels too): what each panel shows, for someone who does not read code
PLAIN_TITLES = {"semantic": "What it has mapped: which of this world's landmarks, or nothing",
                "relevance": "Where it thinks the named landmark is",
                "goal": "Where it thinks the goal is"}
SHOWN = tuple(PLAIN_TITLES)


def heads_for(runner, episode: Episode) -> MapHeads | None:
    """The heads that read the episode's maps: its model's when loaded, else read from its checkpoint folder (an
    episode kept from an earlier server); None when no model watched it or its checkpoint is gone."""
    if episode.checkpoint is None:
        return None
    model = runner.models.get(episode.checkpoint)
    if model is not None:
        return model.heads
    cache = runner.__dict__.setdefault("_export_heads", {})
    if episode.checkpoint not in cache:
        try:
            from gsmn.model.checkpoint import load_checkpoint

            cache[episode.checkpoint] = MapHeads.of(load_checkpoint(Path(episode.checkpoint))[0])
        except Exception:  # noqa: BLE001 - the export goes on without maps, and says so
            cache[episode.checkpoint] = None
    return cache[episode.checkpoint]


def result_line(episode: Episode) -> str:
    r = episode.result
    if episode.status != FINISHED or r is None:
        return f"Stopped early ({episode.status}) after {len(episode.steps)} steps"
    how = "said STOP" if r.stopped else "ran out of steps"
    changed = [*(["in an edited world"] if episode.world_edits else []),
               *([f"with {episode.intervention.short()}"] if episode.intervention is not None else [])]
    return (f"{'Success' if r.success else 'Failure'}: {how} after {r.steps} steps, {r.goal_distance:.1f} m from the "
            f"goal, {r.final_side} side (asked {episode.task.instruction.side})"
            + (f"; {', '.join(changed)}" if changed else ""))


def step_layers(episode: Episode, t: int, heads: MapHeads | None, legends: dict | None = None,
                semantic_reading: str = "world") -> dict[str, np.ndarray]:
    """The shown maps of step t as RGB images (one pixel per cell), north up; empty without maps. The semantic map
    is read over this world's landmarks and nothing unless `semantic_reading` is "all". `legends`, when given,
    gets each map's legend (HTML)."""
    record = episode.steps[t]
    if record.maps is None or heads is None:
        return {}
    names = world_names(episode)  # the legend lists this world's only
    layers = map_layers(record.maps.maps, heads, world_names=names, semantic_reading=semantic_reading)
    if legends is not None:
        legends.update({name: layers[name].legend_html for name in SHOWN if name in layers})
    return {name: layers[name].rgb for name in SHOWN if name in layers}


def world_names(episode: Episode) -> tuple[str, ...]:
    return tuple(lm.noun_phrase for lm in episode.task.world.landmarks)


def semantic_key(episode: Episode, heads: MapHeads | None) -> list[tuple[str, tuple[int, int, int]]]:
    """The semantic map's colours in an export, as (label, colour): this world's landmarks (sorted), nothing, and
    the grey of cells not seen yet; empty when no trained perception head reads the map."""
    if heads is None or not heads.perception_trained:
        return []
    names = sorted(set(world_names(episode)))
    palette = name_palette(heads.class_names, names)
    return ([(name, tuple(int(c) for c in palette[k])) for k, name in enumerate(names)]
            + [(NOTHING, OTHER_RGB), ("not seen yet", UNSEEN_RGB)])


def export_episode(episode: Episode, fmt: str, heads: MapHeads | None, config=None) -> bytes:
    if fmt not in FORMATS:
        raise ValueError(f"format must be one of {', '.join(FORMATS)}, got {fmt!r}")
    if not episode.steps:
        raise ValueError(f"episode {episode.id} has no steps to export")
    if fmt == "html":
        return export_html(episode, heads, config).encode("utf-8")
    frames = [frame_image(episode, t, heads) for t in range(len(episode.steps))]
    return gif_bytes(frames) if fmt == "gif" else mp4_bytes(frames)


# -- GIF and MP4 ------------------------------------------------------------------------------------------------------
def _font(size: int) -> ImageFont.ImageFont:
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # Pillow without FreeType
        return ImageFont.load_default()


def frame_image(episode: Episode, t: int, heads: MapHeads | None, map_px: int = 192) -> np.ndarray:
    """One step for slides: the camera image (scaled to the maps' height) beside the three maps, each titled, and
    under them the step, the instruction and the result."""
    record = episode.steps[t]
    camera = Image.fromarray(decode_image(record.camera_jpeg))
    camera = camera.resize((round(camera.width * map_px / camera.height), map_px), Image.BILINEAR)
    maps = step_layers(episode, t, heads)
    key = semantic_key(episode, heads) if "semantic" in maps else []
    title_h, caption_h, gap = 22, 58 + (22 if key else 0), 8
    width = gap + camera.width + gap + len(maps) * (map_px + gap)
    canvas = Image.new("RGB", (max(width, 640), title_h + map_px + caption_h), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    small, big = _font(13), _font(17)
    canvas.paste(camera, (gap, title_h))
    draw.text((gap, 4), "What the drone sees", fill=(20, 20, 20), font=small)
    x = gap + camera.width + gap
    short = {"semantic": "What it has mapped", "relevance": "Named landmark", "goal": "Goal"}
    for name, rgb in maps.items():
        factor = max(1, map_px // rgb.shape[0])
        image = Image.fromarray(upscale(rgb, factor)).resize((map_px, map_px), Image.NEAREST)
        canvas.paste(image, (x, title_h))
        draw.text((x, 4), short[name], fill=(20, 20, 20), font=small)
        x += map_px + gap
    if not maps:
        draw.text((x, title_h + map_px // 2), "no model maps", fill=(120, 120, 120), font=small)
    y = title_h + map_px + 6
    draw.text((gap, y), f"Step {t} of {len(episode.steps) - 1}   \u201c{episode.instruction}\u201d", fill=(0, 0, 0),
              font=big)
    r = episode.result
    colour = (30, 132, 73) if r is not None and r.success else (192, 57, 43) if r is not None else (90, 90, 90)
    draw.text((gap, y + 26), result_line(episode), fill=colour, font=small)
    _draw_key(draw, key, gap, y + 48, canvas.width - gap, small)
    return np.asarray(canvas)


def _draw_key(draw: ImageDraw.ImageDraw, key: list, x: int, y: int, right: int, font) -> None:
    """The semantic map's legend in one line: "What it has mapped:", then a swatch and a name per colour (those
    that do not fit before `right` are left out)."""
    if not key:
        return
    draw.text((x, y), "What it has mapped:", fill=(20, 20, 20), font=font)
    x += round(draw.textlength("What it has mapped:", font=font)) + 8
    for label, rgb in key:
        width = 14 + round(draw.textlength(label, font=font)) + 12
        if x + width > right:
            break
        draw.rectangle((x, y + 3, x + 10, y + 13), fill=rgb, outline=(150, 150, 150))
        draw.text((x + 14, y), label, fill=(20, 20, 20), font=font)
        x += width


def gif_bytes(frames: list[np.ndarray]) -> bytes:
    images = [Image.fromarray(f).quantize(colors=255, method=Image.Quantize.FASTOCTREE) for f in frames]
    out = io.BytesIO()
    images[0].save(out, format="GIF", save_all=True, append_images=images[1:], duration=1000 // STEPS_PER_SECOND,
                   loop=0, optimize=False, disposal=1)
    return out.getvalue()


def mp4_bytes(frames: list[np.ndarray]) -> bytes:
    try:
        import imageio.v3 as iio
        import imageio_ffmpeg  # noqa: F401 - the encoder imageio writes MP4 with
    except ImportError:
        raise ValueError("MP4 needs ffmpeg (the imageio-ffmpeg package), which is not installed here; export a GIF "
                         "(format=gif) instead") from None
    h, w = (frames[0].shape[0] // 2) * 2, (frames[0].shape[1] // 2) * 2  # H.264 wants even sizes
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "episode.mp4"
        iio.imwrite(path, np.stack([f[:h, :w] for f in frames]), fps=STEPS_PER_SECOND, codec="libx264")
        return path.read_bytes()


# -- the HTML page -----------------------------------------------------------------------------------------------------
def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def export_html(episode: Episode, heads: MapHeads | None, config=None) -> str:
    """A page that plays the episode back with no server: every step's camera and maps embedded."""
    world = episode.task.world
    steps = []
    for t, s in enumerate(episode.steps):
        legends: dict[str, str] = {}
        maps = {name: _b64(png_bytes(upscale(rgb, max(1, 160 // rgb.shape[0]))))
                for name, rgb in step_layers(episode, t, heads, legends).items()}
        p = s.decisive_stop_probability
        steps.append({"camera": _b64(s.camera_jpeg), "maps": maps, "legend": legends.get("semantic", ""),
                      "x": round(s.position[0], 3),
                      "y": round(s.position[1], 3), "v": round(s.v, 3), "omega": round(s.omega, 3),
                      "stop_p": None if p is None else round(p, 3), "stop": s.stop})
    i = episode.task.instruction
    data = {"id": episode.id, "env_id": episode.env_id, "instruction": episode.instruction, "steps": steps,
            "field": world.field_size, "goal": [i.goal_x, i.goal_y],
            "path": np.asarray(episode.task.path).round(3).tolist(),
            "landmarks": [{"name": lm.noun_phrase, "x": lm.x, "y": lm.y} for lm in world.landmarks],
            "titles": PLAIN_TITLES, "result": result_line(episode),
            "success": None if episode.result is None else episode.result.success,
            "policy": {"model": "the model", "mirror": "the model as a mirror ensemble"}.get(episode.policy,
                                                                                          "the expert")}
    payload = json.dumps(data).replace("</", "<\\/")
    title = html.escape(f"Episode {episode.id}: {episode.instruction}")
    return _PAGE.replace("__TITLE__", title).replace("__DATA__", payload)


_PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>__TITLE__</title>
<meta name="viewport" content="width=device-width, initial-scale=1">
<style>
body{font-family:system-ui,sans-serif;margin:16px;color:#1a1a1a;background:#fafafa}
h1{font-size:22px;margin:0 0 4px} .result{font-size:17px;font-weight:600;margin:4px 0 12px}
.ok{color:#1e8449} .bad{color:#c0392b} .row{display:flex;flex-wrap:wrap;gap:14px;align-items:flex-start}
figure{margin:0} figcaption{font-size:13px;font-weight:600;margin-bottom:3px;max-width:200px}
figure .gsmn-legend{max-width:200px;margin-top:3px}
img.map{width:200px;height:200px;image-rendering:pixelated;border-radius:3px}
img.cam{height:200px;border-radius:3px} canvas{background:#e9f0dc;border-radius:3px}
.controls{margin:14px 0;display:flex;gap:10px;align-items:center;font-size:15px}
input[type=range]{width:min(640px,60vw)} button{font-size:15px;padding:4px 14px}
.readout{font-size:14px;color:#333} .note{font-size:12px;color:#666;margin-top:14px}
</style></head><body>
<h1 id="title"></h1><div id="result" class="result"></div>
<div class="controls"><button id="play">Play</button>
<input id="slider" type="range" min="0" value="0" step="1"><span id="stepLabel"></span></div>
<div class="row">
<figure><figcaption>What the drone sees</figcaption><img id="camera" class="cam" alt="camera"></figure>
<figure><figcaption>Seen from above: the path flown (blue), the demonstration path (red dashes) to
the goal (red dot)</figcaption>
<canvas id="top" width="200" height="200"></canvas></figure>
<div id="maps" class="row"></div></div>
<p id="readout" class="readout"></p>
<p class="note">Exported from the GSMN dashboard. Maps north up, one square per map cell; the colour scale of the
landmark and goal maps runs from dark (unlikely) to yellow (likely).</p>
<script>
const D = __DATA__;
const $ = id => document.getElementById(id);
$("title").textContent = `Episode ${D.id}: "${D.instruction}" (environment ${D.env_id}, ${D.policy} flying)`;
$("result").textContent = D.result;
$("result").className = "result " + (D.success === true ? "ok" : D.success === false ? "bad" : "");
const slider = $("slider"); slider.max = D.steps.length - 1;
const mapImgs = {};
for (const name of Object.keys(D.titles)) {
  if (!D.steps.some(s => s.maps[name])) continue;
  const fig = document.createElement("figure");
  fig.innerHTML = `<figcaption>${D.titles[name]}</figcaption>`;
  const img = document.createElement("img"); img.className = "map"; img.dataset.layer = name;
  fig.appendChild(img); $("maps").appendChild(fig); mapImgs[name] = img;
  if (name === "semantic") { const key = document.createElement("div"); key.id = "legend"; fig.appendChild(key); }
}
// a landmark's name beside its dot, turned to the dot's left or below it where it would leave the canvas
function labelAt(g, text, x, y, width, height) {
  const w = g.measureText(text).width;
  const left = x + 4 + w <= width - 1 ? x + 4 : Math.max(1, x - 4 - w);
  return [left, y - 3 - 8 >= 0 ? y - 3 : Math.min(height - 2, y + 12)];
}
function drawTop(t) {
  const c = $("top"), g = c.getContext("2d"), k = c.width / D.field;
  const X = x => x * k, Y = y => c.height - y * k;
  g.clearRect(0, 0, c.width, c.height);
  g.fillStyle = "#555"; g.font = "10px sans-serif";
  for (const l of D.landmarks) {
    g.beginPath(); g.arc(X(l.x), Y(l.y), 3, 0, 7); g.fill();
    const [tx, ty] = labelAt(g, l.name, X(l.x), Y(l.y), c.width, c.height); g.fillText(l.name, tx, ty);
  }
  g.strokeStyle = "#d03030"; g.setLineDash([4, 3]); g.beginPath();
  D.path.forEach((p, i) => i ? g.lineTo(X(p[0]), Y(p[1])) : g.moveTo(X(p[0]), Y(p[1]))); g.stroke(); g.setLineDash([]);
  g.fillStyle = "#d03030"; g.beginPath(); g.arc(X(D.goal[0]), Y(D.goal[1]), 5, 0, 7); g.fill();
  g.strokeStyle = "#2870f5"; g.lineWidth = 2; g.beginPath();
  for (let i = 0; i <= t; i++) { const s = D.steps[i]; i ? g.lineTo(X(s.x), Y(s.y)) : g.moveTo(X(s.x), Y(s.y)); }
  g.stroke(); g.lineWidth = 1;
  const s = D.steps[t]; g.fillStyle = "#2870f5"; g.beginPath(); g.arc(X(s.x), Y(s.y), 4, 0, 7); g.fill();
}
function show(t) {
  const s = D.steps[t];
  slider.value = t; $("camera").src = "data:image/jpeg;base64," + s.camera;
  for (const [name, img] of Object.entries(mapImgs))
    img.src = s.maps[name] ? "data:image/png;base64," + s.maps[name] : "";
  if ($("legend")) $("legend").innerHTML = s.legend;
  $("stepLabel").textContent = `Step ${t} of ${D.steps.length - 1}`;
  $("readout").textContent = `Flying ${s.v.toFixed(2)} m/s, turning ${s.omega.toFixed(2)} rad/s` +
    (s.stop_p === null ? "" : `, P(stop) ${s.stop_p.toFixed(2)}`) + (s.stop ? ": STOP" : "");
  document.body.dataset.step = t; drawTop(t);
}
let timer = null;
function pause() { clearInterval(timer); timer = null; $("play").textContent = "Play"; }
$("play").onclick = () => {
  if (timer) return pause();
  if (+slider.value >= D.steps.length - 1) show(0);
  $("play").textContent = "Pause";
  timer = setInterval(() => { const t = +slider.value + 1; if (t >= D.steps.length) pause(); else show(t); }, 200);
};
slider.oninput = () => { pause(); show(+slider.value); };
show(0);
</script></body></html>
"""
