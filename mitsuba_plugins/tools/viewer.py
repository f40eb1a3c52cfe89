"""``report.html``: a comparison as one self-contained page that works offline (no CDN, no
server: opening the file is enough).

The page holds every image as HDR half floats (base64) and tone-maps them itself, so the
exposure can change; for each integrator also its per-pixel relative squared error and its
HDR-FLIP map (``tools.metrics``), drawn in false colour. One image at a time is shown
large; keys 1-9 or the arrow keys flip between them, ``m`` cycles image / rel. error /
FLIP, ``+``/``-`` change the exposure, ``0`` resets it. A row of zoom views, one per image,
follows the cursor over the large one. Below: the metric table (the same numbers as
``results.json``, which the page also carries in ``<script id="report-data">``) and the
error-against-time curves of every metric.

The gallery's index (:func:`write_index`) links one such page per scene.
"""
from __future__ import annotations

import base64
import html
import math
from pathlib import Path

import numpy as np

from mitsuba_plugins import output
from mitsuba_plugins.tools import metrics
from mitsuba_plugins.tools.compare import Report

HALF_MAX = 65504.0
#: magnification of the large view (at most this many screen pixels per image pixel) and
#: its target width
MAX_SCALE, VIEW_WIDTH = 8, 512
#: image pixels across a zoom view, and its size on screen
ZOOM_PIXELS, ZOOM_SIZE = 16, 144


def _half_b64(array: np.ndarray) -> str:
    """Little-endian float16 bytes of ``array`` (clamped to the half range), base64."""
    x = np.nan_to_num(np.asarray(array, np.float64), nan=0.0, posinf=HALF_MAX, neginf=-HALF_MAX)
    return base64.b64encode(np.clip(x, -HALF_MAX, HALF_MAX).astype("<f2").tobytes()).decode()


def _rgb(image: np.ndarray) -> np.ndarray:
    x = np.asarray(image, np.float64)
    if x.ndim == 2:
        x = x[..., None]
    return np.repeat(x, 3, axis=2) if x.shape[2] == 1 else x[..., :3]


def _magma() -> str:
    """The colour map of the error views: matplotlib's magma, 256 RGB bytes, base64."""
    from matplotlib import colormaps
    lut = (colormaps["magma"](np.linspace(0, 1, 256))[:, :3] * 255 + 0.5).astype(np.uint8)
    return base64.b64encode(lut.tobytes()).decode()


def page_data(report: Report) -> dict:
    """What the page's script draws: the layers (each reference, then each row) with their
    images and error maps, and the range of the relative-error colour scale."""
    layers, relerr = [], []
    for name, ref in report.references.items():
        err = metrics.reference_rel_var(ref)
        relerr.append(err)
        layers.append({"name": f"reference {name}", "kind": "reference",
                       "note": f"{ref.spp} spp; error views: its own relative variance, no FLIP",
                       "image": _half_b64(_rgb(ref.mean)), "relerr": _half_b64(err), "flip": None})
    for row in report.rows:
        ref = report.references[row.reference]
        err = metrics.pixel_rel_se(row.image, ref.mean)
        relerr.append(err)
        flip_map = metrics.flip(row.image, ref.mean)[1]
        layers.append({"name": row.integrator, "kind": "built-in" if row.builtin else "ours",
                       "note": f"{row.spp} spp, {row.seconds:.2f} s; against {row.reference}",
                       "image": _half_b64(_rgb(row.image)), "relerr": _half_b64(err),
                       "flip": _half_b64(flip_map)})
    positive = np.concatenate([e[e > 0].ravel() for e in relerr] + [np.array([1e-8])])
    low = max(float(np.percentile(positive, 1)), 1e-8)
    high = max(float(np.percentile(positive, 99.5)), 10 * low)
    height, width = report.rows[0].image.shape[:2]
    return {"width": int(width), "height": int(height), "layers": layers,
            "relerr_range": [low, high], "magma": _magma(),
            "zoom_pixels": ZOOM_PIXELS, "zoom_size": ZOOM_SIZE,
            "scale": int(max(1, min(MAX_SCALE, VIEW_WIDTH // max(width, 1))))}


def _cell(value, fmt: str) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return fmt.format(value)


def table_html(report: Report, columns) -> str:
    """The metric table; each cell carries its row's JSON key (``data-key``) so that the
    page's numbers can be checked against ``report-data``."""
    head = "".join(f"<th>{html.escape(title)}</th>" for title, _, _ in columns)
    body = []
    for k, row in enumerate(report.rows):
        cells = "".join(f'<td data-key="{attr}">{html.escape(_cell(getattr(row, attr), fmt))}</td>'
                        for _, attr, fmt in columns)
        body.append(f'<tr data-row="{k}" class="{"builtin" if row.builtin else "ours"}">{cells}</tr>')
    return (f'<table id="metrics"><thead><tr>{head}</tr></thead><tbody>{"".join(body)}'
            "</tbody></table>")


def _script_json(value) -> str:
    """JSON safe inside a <script> element."""
    return output.dumps_json(value).replace("</", "<\\/")


def render_page(report: Report, columns, legend: str, curves: Path | None = None,
                title: str | None = None, links: dict | None = None) -> str:
    """The page's HTML. ``columns``: the table's (title, attribute, format) triples;
    ``legend``: the text under it; ``curves``: a PNG to embed; ``links``: text -> href
    shown at the top (the gallery's index)."""
    title = title or f"{Path(report.scene).stem} ({report.mode})"
    curves_html = ""
    if curves is not None:
        png = base64.b64encode(Path(curves).read_bytes()).decode()
        curves_html = (f'<h2>Error against time</h2><img id="curves" alt="error against time" '
                       f'src="data:image/png;base64,{png}">')
    nav = " · ".join(f'<a href="{html.escape(href)}">{html.escape(text)}</a>'
                     for text, href in (links or {}).items())
    return PAGE.format(
        title=html.escape(title), nav=nav, legend=html.escape(legend),
        table=table_html(report, columns), curves=curves_html,
        data=_script_json(page_data(report)), report=_script_json(report.to_dict()),
        style=STYLE, script=SCRIPT)


def write_page(report: Report, path: Path, columns, legend: str, curves: Path | None = None,
               title: str | None = None, links: dict | None = None) -> Path:
    return output.write_text(path, render_page(report, columns, legend, curves, title, links))


def write_index(path: Path, title: str, intro: str, entries: list) -> Path:
    """An index page: ``entries`` of (scene name, page href, summary text)."""
    items = "".join(f'<li><a href="{html.escape(href)}">{html.escape(name)}</a> '
                    f"{html.escape(summary)}</li>" for name, href, summary in entries)
    text = (f'<!doctype html><html lang="en"><head><meta charset="utf-8"><title>'
            f"{html.escape(title)}</title><style>{STYLE}</style></head><body>"
            f"<h1>{html.escape(title)}</h1><p>{html.escape(intro)}</p><ul>{items}</ul>"
            "</body></html>\n")
    return output.write_text(path, text)


PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>{title}</title><style>{style}</style></head>
<body>
<nav>{nav}</nav>
<h1>{title}</h1>
<div id="controls">
  <div id="layers" role="group" aria-label="image"></div>
  <div id="modes" role="group" aria-label="view">
    <button data-mode="image">image</button><button data-mode="relerr">rel. error</button><button data-mode="flip">FLIP</button>
  </div>
  <label>exposure <input id="exposure" type="range" min="-10" max="10" step="0.25" value="0">
  <output id="exposure-value">0</output> EV</label>
</div>
<p class="help">Keys: 1-9 or &larr;/&rarr; flip between images, m cycles image / rel. error / FLIP,
+/- change the exposure, 0 resets it. The zoom views follow the cursor over the large image; a click on one shows its image large.</p>
<div id="stage">
  <div><canvas id="main"></canvas><div id="caption"></div><div id="pixel"></div>
  <div id="colorbar"><canvas id="bar" width="256" height="12"></canvas><span id="bar-low"></span><span id="bar-high"></span></div></div>
  <div id="zooms"></div>
</div>
<h2>Metrics</h2>
{table}
<pre id="legend">{legend}</pre>
{curves}
<script type="application/json" id="viewer-data">{data}</script>
<script type="application/json" id="report-data">{report}</script>
<script>{script}</script>
</body></html>
"""

STYLE = """
body { font-family: system-ui, sans-serif; margin: 1em 2em; background: #fafafa; color: #222; }
nav a { margin-right: .5em; }
#controls { display: flex; flex-wrap: wrap; gap: 1em; align-items: center; margin: .5em 0; }
#controls button { margin: 0 .15em .2em 0; padding: .25em .6em; border: 1px solid #888;
  background: #fff; border-radius: 3px; cursor: pointer; }
#controls button.active { background: #224; color: #fff; }
.help { font-size: .85em; color: #555; }
#stage { display: flex; flex-wrap: wrap; gap: 1.5em; align-items: flex-start; }
canvas { image-rendering: pixelated; image-rendering: crisp-edges; }
#main { border: 1px solid #444; cursor: crosshair; }
#caption { font-weight: 600; margin-top: .3em; }
#pixel { font-family: monospace; font-size: .85em; min-height: 1.2em; }
#colorbar span { font-size: .8em; margin: 0 .5em; }
#zooms { display: flex; flex-wrap: wrap; gap: .6em; max-width: 760px; }
#zooms figure { margin: 0; text-align: center; font-size: .75em; max-width: 150px; }
#zooms canvas { border: 2px solid transparent; cursor: pointer; }
#zooms canvas.active { border-color: #c22; }
table { border-collapse: collapse; font-size: .85em; margin: .5em 0; }
th, td { border: 1px solid #bbb; padding: .2em .5em; text-align: right; }
th:first-child, td:first-child, th:nth-child(2), td:nth-child(2) { text-align: left; }
tr.builtin { color: #555; }
pre { white-space: pre-wrap; font-size: .8em; }
#curves { max-width: 100%; }
"""

SCRIPT = r"""
"use strict";
(function () {
  const D = JSON.parse(document.getElementById("viewer-data").textContent);
  const W = D.width, H = D.height, N = W * H;

  // half floats -> float32, through a table of all 65536 values
  const HALF = new Float32Array(65536);
  for (let h = 0; h < 65536; h++) {
    const s = h & 0x8000 ? -1 : 1, e = (h >> 10) & 0x1f, f = h & 0x3ff;
    HALF[h] = e === 0 ? s * f * Math.pow(2, -24)
      : e === 31 ? (f ? NaN : s * Infinity) : s * (1 + f / 1024) * Math.pow(2, e - 15);
  }
  function bytes(b64) {
    const bin = atob(b64), out = new Uint8Array(bin.length);
    for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out;
  }
  function halves(b64, count) {
    const u16 = new Uint16Array(bytes(b64).buffer), out = new Float32Array(u16.length);
    if (u16.length !== count) throw new Error("image of " + u16.length + " values, expected " + count);
    for (let i = 0; i < u16.length; i++) {
      out[i] = HALF[u16[i]];
      if (!Number.isFinite(out[i])) throw new Error("non-finite value in an image");
    }
    return out;
  }
  const MAGMA = bytes(D.magma);
  const layers = D.layers.map(l => ({
    name: l.name, kind: l.kind, note: l.note,
    image: halves(l.image, 3 * N), relerr: halves(l.relerr, N),
    flip: l.flip ? halves(l.flip, N) : new Float32Array(N),
    canvas: document.createElement("canvas"),
  }));
  const state = { layer: layers.findIndex(l => l.kind !== "reference"), mode: "image",
                  exposure: 0, x: W >> 1, y: H >> 1 };
  if (state.layer < 0) state.layer = 0;
  const MODES = ["image", "relerr", "flip"];
  const [LOG_LOW, LOG_HIGH] = D.relerr_range.map(Math.log10);

  function srgb(v) {
    v = Math.min(Math.max(v, 0), 1);
    return 255 * (v <= 0.0031308 ? 12.92 * v : 1.055 * Math.pow(v, 1 / 2.4) - 0.055);
  }
  function paint(layer) {
    const c = layer.canvas;
    c.width = W; c.height = H;
    const ctx = c.getContext("2d"), img = ctx.createImageData(W, H), px = img.data;
    const gain = Math.pow(2, state.exposure);
    for (let i = 0; i < N; i++) {
      if (state.mode === "image") {
        for (let k = 0; k < 3; k++) px[4 * i + k] = srgb(gain * layer.image[3 * i + k]);
      } else {
        let t = state.mode === "flip" ? layer.flip[i]
          : (Math.log10(Math.max(layer.relerr[i], 1e-30)) - LOG_LOW) / (LOG_HIGH - LOG_LOW);
        const j = 3 * Math.round(255 * Math.min(Math.max(t, 0), 1));
        px[4 * i] = MAGMA[j]; px[4 * i + 1] = MAGMA[j + 1]; px[4 * i + 2] = MAGMA[j + 2];
      }
      px[4 * i + 3] = 255;
    }
    ctx.putImageData(img, 0, 0);
  }

  const main = document.getElementById("main");
  main.width = W * D.scale; main.height = H * D.scale;
  const zooms = document.getElementById("zooms"), layerButtons = document.getElementById("layers");
  layers.forEach((layer, k) => {
    const b = document.createElement("button");
    b.textContent = (k < 9 ? (k + 1) + ": " : "") + layer.name;
    b.title = layer.kind + "; " + layer.note;
    b.addEventListener("click", () => select(k));
    layerButtons.appendChild(b);
    layer.button = b;
    const fig = document.createElement("figure"), z = document.createElement("canvas");
    z.width = z.height = D.zoom_size;
    z.addEventListener("click", () => select(k));
    const cap = document.createElement("figcaption");
    cap.textContent = layer.name;
    fig.appendChild(z); fig.appendChild(cap); zooms.appendChild(fig);
    layer.zoom = z;
  });

  function drawMain() {
    const ctx = main.getContext("2d"), layer = layers[state.layer];
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(layer.canvas, 0, 0, W * D.scale, H * D.scale);
    const half = D.zoom_pixels / 2, s = D.scale;   // the zoomed square
    ctx.strokeStyle = "rgba(255,64,64,0.9)"; ctx.lineWidth = 1;
    ctx.strokeRect((state.x - half) * s + 0.5, (state.y - half) * s + 0.5, D.zoom_pixels * s, D.zoom_pixels * s);
    const view = { image: "image", relerr: "relative squared error (log scale)", flip: "HDR-FLIP" }[state.mode];
    document.getElementById("caption").textContent =
      layer.name + " (" + layer.kind + ") - " + view + (state.mode === "image"
        ? ", exposure " + state.exposure.toFixed(2) + " EV" : "") + " - " + layer.note;
    layers.forEach((l, k) => { l.button.classList.toggle("active", k === state.layer);
                                l.zoom.classList.toggle("active", k === state.layer); });
    document.querySelectorAll("#modes button").forEach(
      b => b.classList.toggle("active", b.dataset.mode === state.mode));
  }
  function drawZooms() {
    const half = D.zoom_pixels / 2;
    for (const layer of layers) {
      const ctx = layer.zoom.getContext("2d");
      ctx.imageSmoothingEnabled = false;
      ctx.fillStyle = "#000"; ctx.fillRect(0, 0, D.zoom_size, D.zoom_size);
      ctx.drawImage(layer.canvas, state.x - half, state.y - half, D.zoom_pixels, D.zoom_pixels,
                    0, 0, D.zoom_size, D.zoom_size);
    }
    const l = layers[state.layer], i = state.y * W + state.x;
    const rgb = [0, 1, 2].map(k => l.image[3 * i + k].toPrecision(4)).join(" ");
    document.getElementById("pixel").textContent = "pixel (" + state.x + ", " + state.y +
      "): " + rgb + "; rel. sq. error " + l.relerr[i].toPrecision(3) +
      (l.kind === "reference" ? "" : "; FLIP " + l.flip[i].toFixed(3));
  }
  function drawBar() {
    const ctx = document.getElementById("bar").getContext("2d");
    for (let k = 0; k < 256; k++) {
      ctx.fillStyle = "rgb(" + MAGMA[3 * k] + "," + MAGMA[3 * k + 1] + "," + MAGMA[3 * k + 2] + ")";
      ctx.fillRect(k, 0, 1, 12);
    }
    const show = state.mode !== "image";
    document.getElementById("colorbar").style.visibility = show ? "visible" : "hidden";
    document.getElementById("bar-low").textContent = state.mode === "flip" ? "0" : D.relerr_range[0].toExponential(1);
    document.getElementById("bar-high").textContent = state.mode === "flip" ? "1" : D.relerr_range[1].toExponential(1);
  }
  function repaint() { layers.forEach(paint); drawMain(); drawZooms(); drawBar(); }
  function select(k) { state.layer = (k + layers.length) % layers.length; drawMain(); drawZooms(); }
  function setMode(m) { state.mode = m; repaint(); }
  const slider = document.getElementById("exposure");
  function setExposure(ev) {
    state.exposure = Math.min(10, Math.max(-10, ev));
    slider.value = state.exposure;
    document.getElementById("exposure-value").textContent = state.exposure.toFixed(2);
    repaint();
  }
  slider.addEventListener("input", () => setExposure(parseFloat(slider.value)));
  document.querySelectorAll("#modes button").forEach(b => b.addEventListener("click", () => setMode(b.dataset.mode)));
  main.addEventListener("mousemove", e => {
    const r = main.getBoundingClientRect();
    state.x = Math.min(W - 1, Math.max(0, Math.floor((e.clientX - r.left) / r.width * W)));
    state.y = Math.min(H - 1, Math.max(0, Math.floor((e.clientY - r.top) / r.height * H)));
    drawMain(); drawZooms();
  });
  document.addEventListener("keydown", e => {
    if (e.target instanceof HTMLInputElement && e.key !== "Escape") return;
    if (e.key >= "1" && e.key <= "9" && +e.key <= layers.length) select(+e.key - 1);
    else if (e.key === "ArrowRight") select(state.layer + 1);
    else if (e.key === "ArrowLeft") select(state.layer - 1);
    else if (e.key === "m") setMode(MODES[(MODES.indexOf(state.mode) + 1) % MODES.length]);
    else if (e.key === "+" || e.key === "=") setExposure(state.exposure + 0.5);
    else if (e.key === "-") setExposure(state.exposure - 0.5);
    else if (e.key === "0") setExposure(0);
    else return;
    e.preventDefault();
  });
  repaint();
  window.viewerState = state;
  window.viewerDecoded = layers.length;
  document.body.dataset.ready = "true";
})();
"""
