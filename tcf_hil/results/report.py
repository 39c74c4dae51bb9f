"""The run report: one self-contained HTML file, readable offline with no network fetch.

What it shows, from the run directory alone (``build_report``; ``write_report`` at the end
of every scored run):

- a map: the terrain shaded with contour lines (from the ground truth's closed formula), the
  cloud's top view, the track with its direction, every ground-truth stem coloured by its
  outcome (:func:`tcf_hil.results.export.stem_outcomes`: correct, misclassified, missed though seen,
  missed and unseen) and the SIC's stems (false positives marked); hover for a stem's facts,
  click to pin them and find its row; wheel to zoom, drag to pan, layers to switch;
- the accumulated cloud in 3D (a decimated sample of every k-th frame, stems coloured by id):
  drag to turn, wheel to zoom, shift-drag to pan;
- the per-stem table (sortable, filterable, downloadable as CSV: the export's columns);
- errors against distance from the track (position, DBH) and by distance band;
- the score timeline with the injected faults below it; the scores and evaluation matrices;
  the run's figures as tables.

The libraries are none: the map and charts are SVG written here, the 3D view a 2D canvas
with a depth buffer filled by a few dozen lines of script (``report_assets/report.js``).
Plotly's offline bundle alone is 3.5 MB and needs WebGL for 10^5 points; a 2D canvas draws
120,000 points in tens of milliseconds on any browser, with or without a GPU, headless too.
"""

from __future__ import annotations

import base64
import html
import json
import math
import re
from collections.abc import Callable
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil._io import read_json, write_bytes_atomic
from tcf_hil.errors import InputError
from tcf_hil.evaluation import LABELS, ROWS, show_metric

if TYPE_CHECKING:
    from tcf_hil.evaluation.scoring import ScoredForest

__all__ = ["CLOUD_POINTS", "OUTCOMES", "build_report", "write_report"]

CLOUD_FRAMES = 40
"""The 3D view and the top view read about this many frames, spread evenly over the run,
each from its own window of the capture (:func:`tcf_hil.results.export.run_cloud`'s ``sample``):
the cost is these frames', whatever the run's length."""
CLOUD_POINTS = 120_000
"""At most this many points in the 3D view (two thirds for what is not ground), 9 bytes
each before base64: about 1.4 MB in the page."""
_MAP_PX = 1600  # the rasters' longest side, pixels

#: outcome: (label, colour). The Okabe-Ito palette, distinguishable with colour blindness
OUTCOMES: dict[str, tuple[str, str]] = {
    "correct": ("correct", "#009E73"),
    "misclassified": ("misclassified", "#E69F00"),
    "missed_seen": ("missed, though seen", "#D55E00"),
    "missed_unseen": ("missed, not seen", "#8C8C8C"),
    "false_positive": ("SIC false positive", "#0072B2"),
    "matched": ("SIC stem, matched", "#222222"),
}

Say = Callable[[str], None]


# ---------------------------------------------------------------------------- entry points

def write_report(path: Path, run_dir: str | Path, manifest: dict[str, Any] | None = None,
                 say: Say | None = None, scored: ScoredForest | None = None) -> None:
    """The report of a finished run (its directory holds score.json and the recording),
    written to ``path`` under a temporary name, then renamed. ``scored``: the final forest
    as the run scored it (else scored again from the directory)."""
    doc = build_report(run_dir, manifest, say=say, scored=scored)
    write_bytes_atomic(path, doc.encode("utf-8"))


def build_report(run_dir: str | Path, manifest: dict[str, Any] | None = None,
                 say: Say | None = None, scored: ScoredForest | None = None) -> str:
    """The report of the run in ``run_dir`` as one HTML document."""
    run = Path(run_dir)
    score_path = run / "score.json"
    if not score_path.exists():
        raise InputError(str(score_path), "", "missing: the run was not scored")
    score = read_json(score_path)
    if manifest is None:
        manifest = read_json(run / "manifest.json") if (run / "manifest.json").exists() else {}
    from tcf_hil.results.export import STEM_COLUMNS, stem_outcomes, track_xy

    if scored is not None:  # as the run read them: the truth and the track
        gt_doc: dict[str, Any] | None = scored.truth_doc
        track = scored.track if scored.track is not None else track_xy(run)
    else:
        gt_doc = read_json(run / "ground_truth.json") \
            if (run / "ground_truth.json").exists() else None
        track = track_xy(run)  # (every 64th column: millimetres apart, fine for drawing too)
    gts, obs = stem_outcomes(run, gt_doc, track, scored)
    frame = _Frame.around(gts, obs, track)
    cloud = _cloud(run, frame, manifest, say)
    terrain = _terrain((gt_doc or {}).get("terrain"), frame)
    faults = _fault_events(run)
    view3d: dict[str, Any] | None = cloud.pop("view3d", None) if cloud else None
    data = {"stems": gts, "sic": obs, "columns": list(STEM_COLUMNS),
            "outcomes": {k: list(v) for k, v in OUTCOMES.items()},
            "cloud": view3d}
    title = f"tcf-hil run: {manifest.get('scenario') or run.name} {manifest.get('mode') or ''}"
    parts = {
        "title": html.escape(title),
        "head": _head(score, manifest, gts, obs),
        "map": _map_svg(frame, gts, obs, track, terrain, cloud),
        "map_note": _map_note(terrain, cloud, track),
        "cloud_note": _cloud_note(cloud, view3d),
        "errors": _errors(gts),
        "timeline": _timeline(score.get("timeline") or [], faults, manifest),
        "scores": _scores(score),
        "figures": _figures(manifest, run),
        "css": _asset("report.css"),
        "js": _asset("report.js"),
        "data": _json_script(data),
    }
    # one pass: what is put in is not searched again (a scenario named "{{js}}" stays so)
    return re.sub(r"\{\{(\w+)\}\}", lambda m: parts[m.group(1)], _PAGE)


def _asset(name: str) -> str:
    return (resources.files("tcf_hil") / "report_assets" / name).read_text(encoding="utf-8")


def _json_script(data: Any) -> str:
    """JSON for a ``<script type="application/json">``: ``</`` cannot end the element."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False, default=_plain)
    return text.replace("</", "<\\/")


def _plain(v: Any) -> Any:
    if isinstance(v, np.integer):
        return int(v)
    if isinstance(v, np.floating):
        return None if math.isnan(float(v)) else round(float(v), 4)
    raise TypeError(f"not JSON: {type(v).__name__}")


# ---------------------------------------------------------------------------- the map frame

class _Frame:
    """The map's extent: world (x, y) to map (u, v) metres with v down (north up), and the
    rasters' cell size."""

    def __init__(self, x0: float, y1: float, w: float, h: float) -> None:
        self.x0, self.y1, self.w, self.h = x0, y1, w, h
        self.cell = max(0.05, max(w, h) / _MAP_PX)
        self.nx = max(1, math.ceil(w / self.cell))
        self.ny = max(1, math.ceil(h / self.cell))

    @classmethod
    def around(cls, gts: list[dict[str, Any]], obs: list[dict[str, Any]],
               track: NDArray[np.float64]) -> _Frame:
        xy = [(r["x"], r["y"]) for r in gts + obs] + [tuple(p) for p in track]
        a = np.asarray(xy, np.float64).reshape(-1, 2)
        a = a[np.isfinite(a).all(1)]
        if not len(a):
            a = np.zeros((1, 2))
        lo, hi = a.min(0), a.max(0)
        pad = max(3.0, 0.04 * float((hi - lo).max()))
        x0, y0 = math.floor(lo[0] - pad), math.floor(lo[1] - pad)
        x1, y1 = math.ceil(hi[0] + pad), math.ceil(hi[1] + pad)
        return cls(float(x0), float(y1), float(x1 - x0), float(y1 - y0))

    def uv(self, x: Any, y: Any) -> tuple[Any, Any]:
        return np.asarray(x) - self.x0, self.y1 - np.asarray(y)

    def centres(self) -> tuple[NDArray[Any], NDArray[Any]]:
        """World x of the raster's columns and y of its rows (row 0 the northmost)."""
        return (self.x0 + (np.arange(self.nx) + 0.5) * self.cell,
                self.y1 - (np.arange(self.ny) + 0.5) * self.cell)


def _png_uri(img: NDArray[np.uint8]) -> str:
    from protocols.png import encode_png

    return "data:image/png;base64," + base64.b64encode(encode_png(img)).decode()


def _nice(span: float, n: int = 6) -> float:
    """A round step (1, 2 or 5 times a power of ten) giving about ``n`` steps over ``span``."""
    if not span > 0 or not math.isfinite(span):
        return 1.0
    raw = span / n
    p = 10 ** math.floor(math.log10(raw))
    return next(m * p for m in (1, 2, 5, 10) if m * p >= raw)


# ---------------------------------------------------------------------------- terrain

def _terrain(doc: dict[str, Any] | None, fr: _Frame) -> dict[str, Any] | None:
    """The terrain as a shaded relief with contour lines (a PNG over the map's frame):
    the ground truth's height formula evaluated at every cell; light from the north-west
    at 45 degrees, the cartographic convention."""
    if not isinstance(doc, dict) or "elevation_m" not in doc:
        return None
    from tcf_hil.world.terrain import Terrain

    ter = Terrain.from_doc(doc)
    ox, oy, oz = (float(v) for v in doc.get("origin", (0.0, 0.0, 0.0)))
    # coarser than the cloud: the relief is smooth; at most 800 cells a side
    step = max(1, math.ceil(max(fr.nx, fr.ny) / 800))
    xs, ys = fr.centres()
    xs, ys = xs[::step], ys[::step]
    z = oz + ter.lattice_height(xs - ox, ys - oy)
    cell = fr.cell * step
    dzdy_rows, dzdx = np.gradient(z, cell)
    dzdy = -dzdy_rows  # rows go south
    n = np.stack([-dzdx, -dzdy, np.ones_like(z)])
    n /= np.linalg.norm(n, axis=0)
    light = np.array([-0.5, 0.5, math.sqrt(0.5)])  # from the NW (azimuth 315), 45 deg up
    shade = np.clip(np.tensordot(light, n, 1), 0.0, 1.0) / math.sqrt(0.5)
    zmin, zmax = float(z.min()), float(z.max())
    t = (z - zmin) / (zmax - zmin) if zmax - zmin > 1e-6 else np.full_like(z, 0.3)
    low, high = np.array([222, 232, 205]), np.array([214, 196, 160])  # meadow to heath
    rgb = (low + t[..., None] * (high - low)) * np.clip(0.55 + 0.45 * shade, 0, 1.15)[..., None]
    interval = _nice(zmax - zmin, 12) if zmax - zmin > 0.05 else None
    if interval is not None:
        band = np.floor(z / interval)
        edge = np.zeros(z.shape, bool)
        edge[:, 1:] |= band[:, 1:] != band[:, :-1]
        edge[1:, :] |= band[1:, :] != band[:-1, :]
        rgb[edge] *= 0.72
    img = np.clip(rgb, 0, 255).astype(np.uint8)
    return {"uri": _png_uri(img), "zmin": zmin, "zmax": zmax, "contour_m": interval,
            "slope_max_deg": float(np.degrees(np.arctan(np.hypot(dzdx, dzdy).max())))}


# ---------------------------------------------------------------------------- the cloud

_PRIORITY = np.zeros(256, np.uint8)  # what shows on top in a top-view cell
_PRIORITY[[2, 7, 1, 3, 5, 64]] = [1, 2, 3, 4, 4, 5]
_TOP_RGBA = np.array([[0, 0, 0, 0], [70, 70, 70, 70], [120, 120, 120, 150],
                      [150, 110, 70, 230], [70, 150, 60, 210], [120, 40, 25, 255]], np.uint8)


def _cloud(run: Path, fr: _Frame, manifest: dict[str, Any], say: Say | None
           ) -> dict[str, Any] | None:
    """The top view (PNG over the map's frame) and the 3D view's sample of the cloud as the
    sensor saw it, from every k-th frame of the capture; None with the reason when the run
    has no capture (a soak) or it cannot be read."""
    from tcf_hil.results.export import run_cloud

    if not (run / "lidar.pcap").exists():
        return {"reason": "This run did not record its lidar traffic (a soak run keeps "
                          "no capture): no cloud to show."}
    frames = int((manifest.get("lidar") or {}).get("frames_sent")
                 or manifest.get("frames_planned") or 400)
    if say:
        say(f"report: reading {min(frames, CLOUD_FRAMES)} frames of the capture for the "
            "cloud views ...")
    keep = ("x", "y", "z", "classification", "stem_id")
    parts: dict[str, list[NDArray[Any]]] = {k: [] for k in keep}
    n_frames = 0
    try:
        info, it = run_cloud(run, sample=(CLOUD_FRAMES, frames))
        for pts in it:
            n_frames += 1
            for k in keep:
                parts[k].append(pts[k])
    except InputError as err:
        return {"reason": f"The cloud could not be read: {err}"}
    if not parts["x"]:
        return {"reason": "The capture holds no return."}
    x, y, z = (np.concatenate(parts[k]) for k in ("x", "y", "z"))
    cls = np.concatenate(parts["classification"])
    sid = np.concatenate(parts["stem_id"])
    n_read = len(x)
    # the top view: per cell the most telling class (stem over vegetation over ground)
    u, v = fr.uv(x, y)
    i = np.floor(u / fr.cell).astype(np.int64)
    j = np.floor(v / fr.cell).astype(np.int64)
    ok = (i >= 0) & (i < fr.nx) & (j >= 0) & (j < fr.ny)
    top = np.zeros(fr.nx * fr.ny, np.uint8)
    np.maximum.at(top, (j[ok] * fr.nx + i[ok]), _PRIORITY[cls[ok]] if info.labelled
                  else np.uint8(2))
    top_uri = _png_uri(_TOP_RGBA[top].reshape(fr.ny, fr.nx, 4))
    # the 3D view: a random sample, two thirds of it kept for what is not ground
    rng = np.random.default_rng(0)
    ground = cls == 2
    idx_g, idx_o = np.flatnonzero(ground), np.flatnonzero(~ground)
    n_o = min(len(idx_o), CLOUD_POINTS * 2 // 3)
    n_g = min(len(idx_g), CLOUD_POINTS - n_o)
    sel = np.sort(np.concatenate([rng.choice(idx_o, n_o, replace=False),
                                  rng.choice(idx_g, n_g, replace=False)]))
    p = np.stack([x[sel], y[sel], z[sel]], 1)
    lo = p.min(0)
    span = float((p.max(0) - lo).max()) or 1.0
    scale = span / 65535.0
    q = np.clip(np.round((p - lo) / scale), 0, 65535).astype("<u2")
    view = {"n": len(sel), "origin": [round(float(c), 3) for c in lo],
            "scale": scale, "labelled": info.labelled,
            "pos": base64.b64encode(q.tobytes()).decode(),
            "cls": base64.b64encode(cls[sel].astype(np.uint8).tobytes()).decode(),
            "sid": base64.b64encode((sid[sel] & 0xFFFF).astype("<u2").tobytes()).decode()}
    return {"top_uri": top_uri, "frames": n_frames, "points_read": n_read,
            "labelled": info.labelled, "view3d": view}


# ---------------------------------------------------------------------------- faults

def _fault_events(run: Path) -> list[dict[str, Any]]:
    from tcf_hil.devices.faults import read_fault_log

    try:
        return read_fault_log(run / "faults.jsonl")
    except (OSError, ValueError):
        return []


# ---------------------------------------------------------------------------- HTML parts

def _f(v: Any, fmt: str = "{:.2f}", none: str = "–") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return none
    return fmt.format(v)


def _head(score: dict[str, Any], man: dict[str, Any], gts: list[dict[str, Any]],
          obs: list[dict[str, Any]]) -> str:
    a = score.get("all_trees") or {}
    count = {k: 0 for k in OUTCOMES}
    for r in gts + obs:
        count[r["outcome"]] = count.get(r["outcome"], 0) + 1
    chips = [("wc, all trees", show_metric("{:.1f} %", a.get("evaluation_score_percent"))),
             ("F1", _f(a.get("f1"), "{:.3f}")),
             ("DBH RMSE", "absent" if a.get("dbh_rmse_m") is None
              else f"{100 * a['dbh_rmse_m']:.1f} cm"),
             ("position RMSE", _f(a.get("position_rmse_m"), "{:.2f} m")),
             ("trees", str(len(gts))), ("SIC stems", str(len(obs)))]
    chip = "".join(f'<div class="chip"><b>{html.escape(v)}</b><span>{html.escape(k)}</span>'
                   f"</div>" for k, v in chips)
    legend = "".join(
        f'<span class="key"><i style="background:{c}"></i>{html.escape(label)} '
        f"<b>{count.get(k, 0)}</b></span>" for k, (label, c) in OUTCOMES.items())
    status = str(score.get("status", man.get("status", "")))
    msg = str(score.get("message") or "")
    bad = "" if status == "complete" else " bad"
    return (f'<p class="status{bad}">Status: <b>{html.escape(status)}</b> '
            f"{html.escape(msg)}</p><div class=chips>{chip}</div>"
            f'<p class="legend">{legend}</p>')


def _map_svg(fr: _Frame, gts: list[dict[str, Any]], obs: list[dict[str, Any]],
             track: NDArray[np.float64], terrain: dict[str, Any] | None,
             cloud: dict[str, Any] | None) -> str:
    w, h = fr.w, fr.h
    out = [f'<svg id="map-svg" viewBox="0 0 {w:g} {h:g}" xmlns="http://www.w3.org/2000/svg" '
           f'data-w="{w:g}" data-h="{h:g}" role="img" aria-label="map of the run">',
           '<defs><path id="arr" d="M-1.2,-1 L1.4,0 L-1.2,1 z"/></defs>',
           f'<rect width="{w:g}" height="{h:g}" fill="#f4f1ea"/>']
    if terrain is not None:
        out.append(f'<g data-layer="terrain"><image href="{terrain["uri"]}" x="0" y="0" '
                   f'width="{w:g}" height="{h:g}" preserveAspectRatio="none" '
                   f'style="image-rendering:auto"/></g>')
    if cloud is not None and "top_uri" in cloud:
        out.append(f'<g data-layer="cloud"><image href="{cloud["top_uri"]}" x="0" y="0" '
                   f'width="{w:g}" height="{h:g}" preserveAspectRatio="none" '
                   f'style="image-rendering:pixelated"/></g>')
    # a scale bar's grid: lines every round step
    step = _nice(max(w, h), 8)
    gx = np.arange(math.ceil(fr.x0 / step) * step, fr.x0 + w + 1e-9, step)
    gy = np.arange(math.ceil((fr.y1 - h) / step) * step, fr.y1 + 1e-9, step)
    grid = [f'<path d="M{x - fr.x0:g},0v{h:g}"/>' for x in gx]
    grid += [f'<path d="M0,{fr.y1 - y:g}h{w:g}"/>' for y in gy]
    out.append('<g data-layer="grid" class="grid">' + "".join(grid) + "</g>")
    if len(track) > 1:
        u, v = fr.uv(track[:, 0], track[:, 1])
        pts = " ".join(f"{a:.2f},{b:.2f}" for a, b in zip(u, v, strict=True))
        arrows = []
        seg = np.hypot(np.diff(u), np.diff(v))
        along = np.concatenate([[0.0], np.cumsum(seg)])
        every = max(2.0, _nice(float(along[-1]), 12))
        for s in np.arange(every / 2, along[-1], every):
            k = int(np.searchsorted(along, s, side="right") - 1)
            k = min(k, len(seg) - 1)
            t = (s - along[k]) / seg[k] if seg[k] > 0 else 0.0
            au, av = u[k] + t * (u[k + 1] - u[k]), v[k] + t * (v[k + 1] - v[k])
            ang = math.degrees(math.atan2(v[k + 1] - v[k], u[k + 1] - u[k]))
            arrows.append(f'<use href="#arr" class="arrow" transform="translate({au:.2f},'
                          f'{av:.2f}) rotate({ang:.1f}) scale(1)"/>')
        out.append(f'<g data-layer="track"><polyline class="track" points="{pts}"/>'
                   + "".join(arrows)
                   + f'<circle class="start" cx="{u[0]:.2f}" cy="{v[0]:.2f}" r="1"/>'
                   + "</g>")
    circles = []
    for i, r in enumerate(gts):
        cu, cv = fr.uv(r["x"], r["y"])
        rad = (r["dbh_m"] or 0.2) / 2
        circles.append(f'<circle data-i="{i}" data-r="{rad:.3f}" cx="{cu:.2f}" '
                       f'cy="{cv:.2f}" r="{max(rad, 0.3):.2f}" '
                       f'fill="{OUTCOMES[r["outcome"]][1]}"/>')
    out.append('<g data-layer="truth" id="truth-g">' + "".join(circles) + "</g>")
    marks, links = [], []
    for j, r in enumerate(obs):
        cu, cv = fr.uv(r["x"], r["y"])
        marks.append(f'<use href="#sic-mark" data-j="{j}" class="{r["outcome"]}" '
                     f'transform="translate({cu:.2f},{cv:.2f})"/>')
    obs_at = {o["id"]: j for j, o in enumerate(obs)}
    for r in gts:
        if r["matched_id"] is not None and r["match_distance_m"]:
            m = obs_at.get(r["matched_id"])
            if m is not None:
                a = fr.uv(r["x"], r["y"])
                b = fr.uv(obs[m]["x"], obs[m]["y"])
                links.append(f"M{a[0]:.2f},{a[1]:.2f}L{b[0]:.2f},{b[1]:.2f}")
    out.append(f'<g data-layer="sic" id="sic-g"><path class="link" d="{"".join(links)}"/>'
               + "".join(marks) + "</g>")
    out.append('<defs><path id="sic-mark" d="M-1,-1 L1,1 M-1,1 L1,-1"/></defs>')
    out.append("</svg>")
    return "".join(out)


def _map_note(terrain: dict[str, Any] | None, cloud: dict[str, Any] | None,
              track: NDArray[np.float64]) -> str:
    bits = []
    if terrain is None:
        bits.append("No terrain model (a field inventory has none).")
    elif terrain["contour_m"] is None:
        bits.append(f"Flat terrain at z = {terrain['zmin']:.1f} m.")
    else:
        bits.append(f"Terrain {terrain['zmin']:.1f}–{terrain['zmax']:.1f} m, contours every "
                    f"{terrain['contour_m']:g} m, steepest {terrain['slope_max_deg']:.0f}°, "
                    "shaded from the north-west.")
    if cloud is not None and "top_uri" in cloud:
        bits.append(f"Cloud top view: {cloud['frames']} frames spread over the run, "
                    f"{cloud['points_read']:,} returns; dark red stems, green vegetation, "
                    "grey ground.")
    elif cloud is not None:
        bits.append(html.escape(cloud["reason"]))
    if len(track) < 2:
        bits.append("No track recorded (no sensor_poses.csv).")
    else:
        bits.append("The track starts at the ring; arrows give the direction.")
    return " ".join(bits)


def _cloud_note(cloud: dict[str, Any] | None, view: dict[str, Any] | None) -> str:
    if view is None:
        return html.escape(cloud["reason"]) if cloud else "No cloud."
    assert cloud is not None
    return (f"{view['n']:,} of the {cloud['points_read']:,} returns of {cloud['frames']} "
            f"frames spread over the run (at most {CLOUD_POINTS:,}; two thirds kept for "
            "what is not ground).")


# ---------------------------------------------------------------------------- charts (SVG)

def _chart(series: list[dict[str, Any]], xlabel: str, ylabel: str, *,
           lanes: list[tuple[str, str, list[tuple[float, int]]]] | None = None,
           ylim: tuple[float, float] | None = None, xlim: tuple[float, float] | None = None,
           zero: bool = False, width: int = 640, height: int = 300) -> str:
    """A scatter or line chart as SVG. ``series``: name, colour, points [(x, y)], ``line``
    (bool); ``lanes``: rows of event ticks below the plot (name, colour, [(x, count)])."""
    lanes = lanes or []
    xs = [p[0] for s in series for p in s["points"]] + [x for _, _, ev in lanes for x, _ in ev]
    ys = [p[1] for s in series for p in s["points"]]
    ml, mr, mt, mb = 58, 12, 10, 44 + 16 * len(lanes)
    pw, ph = width - ml - mr, height - mt - mb
    x0, x1 = xlim or ((min(xs), max(xs)) if xs else (0.0, 1.0))
    y0, y1 = ylim or ((min(ys), max(ys)) if ys else (0.0, 1.0))
    if zero:
        y0, y1 = min(y0, 0.0), max(y1, 0.0)
    if x1 - x0 < 1e-9:
        x0, x1 = x0 - 0.5, x1 + 0.5
    if y1 - y0 < 1e-9:
        y0, y1 = y0 - 0.5, y1 + 0.5
    if ylim is None:
        pad = 0.05 * (y1 - y0)
        y0, y1 = y0 - pad, y1 + pad

    def sx(x: float) -> float:
        return ml + (x - x0) / (x1 - x0) * pw

    def sy(y: float) -> float:
        return mt + (y1 - y) / (y1 - y0) * ph

    out = [f'<svg class="chart" viewBox="0 0 {width} {height}" '
           f'xmlns="http://www.w3.org/2000/svg">']
    out.append(f'<rect x="{ml}" y="{mt}" width="{pw}" height="{ph}" class="plot"/>')
    for tick_step, axis in ((_nice(x1 - x0), "x"), (_nice(y1 - y0, 5), "y")):
        lo, hi = (x0, x1) if axis == "x" else (y0, y1)
        t = math.ceil(lo / tick_step) * tick_step
        while t <= hi + 1e-9:
            label = f"{t:.10g}"
            if axis == "x":
                out.append(f'<path class="tick" d="M{sx(t):.1f},{mt}v{ph}"/>'
                           f'<text x="{sx(t):.1f}" y="{mt + ph + 14}" '
                           f'text-anchor="middle">{label}</text>')
            else:
                out.append(f'<path class="tick" d="M{ml},{sy(t):.1f}h{pw}"/>'
                           f'<text x="{ml - 5}" y="{sy(t) + 4:.1f}" '
                           f'text-anchor="end">{label}</text>')
            t += tick_step
    if zero and y0 < 0 < y1:
        out.append(f'<path class="zero" d="M{ml},{sy(0):.1f}h{pw}"/>')
    for s in series:
        pts = [(sx(x), sy(y)) for x, y in s["points"]]
        if s.get("line") and len(pts) > 1:
            out.append(f'<polyline fill="none" stroke="{s["colour"]}" stroke-width="2" '
                       f'points="{" ".join(f"{a:.1f},{b:.1f}" for a, b in pts)}"/>')
        out.append("".join(f'<circle cx="{a:.1f}" cy="{b:.1f}" r="{s.get("r", 2.6)}" '
                           f'fill="{s["colour"]}" fill-opacity="0.75"/>' for a, b in pts))
    for k, (name, colour, ev) in enumerate(lanes):
        yy = mt + ph + 30 + 16 * k
        out.append(f'<text x="{ml - 5}" y="{yy + 4}" text-anchor="end" class="lane">'
                   f"{html.escape(name)}</text>")
        out.append("".join(
            f'<path stroke="{colour}" stroke-width="2" d="M{sx(x):.1f},{yy - 6}v12">'
            f"<title>{html.escape(name)}: {n} at {x:.1f} s</title></path>"
            for x, n in ev if x0 <= x <= x1))
    out.append(f'<text x="{ml + pw / 2:.0f}" y="{mt + ph + 32 + 16 * len(lanes)}" '
               f'text-anchor="middle" class="axis">{html.escape(xlabel)}</text>')
    out.append(f'<text transform="translate(14,{mt + ph / 2:.0f}) rotate(-90)" '
               f'text-anchor="middle" class="axis">{html.escape(ylabel)}</text>')
    legend = [s for s in series if s.get("name")]
    for k, s in enumerate(legend):
        out.append(f'<circle cx="{ml + 12}" cy="{mt + 12 + 15 * k}" r="4" '
                   f'fill="{s["colour"]}"/><text x="{ml + 20}" y="{mt + 16 + 15 * k}" '
                   f'class="lg">{html.escape(s["name"])}</text>')
    out.append("</svg>")
    return "".join(out)


def _errors(gts: list[dict[str, Any]]) -> str:
    """Position and DBH errors of the matched trees against their distance from the track,
    and detection by distance band."""
    rows = [r for r in gts if r["distance_to_track_m"] is not None]
    if not rows:
        return "<p>No track recorded: no distances.</p>"
    matched = [r for r in rows if r["outcome"] in ("correct", "misclassified")]
    col = {k: OUTCOMES[k][1] for k in ("correct", "misclassified")}
    pos = [{"name": OUTCOMES[k][0], "colour": col[k],
            "points": [(r["distance_to_track_m"], 100 * r["match_distance_m"])
                       for r in matched if r["outcome"] == k
                       and r["match_distance_m"] is not None]} for k in col]
    dbh = [{"name": OUTCOMES[k][0], "colour": col[k],
            "points": [(r["distance_to_track_m"], 100 * (r["observed_dbh_m"] - r["dbh_m"]))
                       for r in matched if r["outcome"] == k
                       and r["observed_dbh_m"] is not None and r["dbh_m"] is not None]}
           for k in col]
    dmax = max(r["distance_to_track_m"] for r in rows)
    xlim = (0.0, max(dmax, 1.0))
    charts = (
        '<div class="charts"><figure>'
        + _chart(pos, "distance from the track, m", "position error, cm", xlim=xlim,
                 zero=True)
        + "<figcaption>Horizontal distance between each matched tree and its SIC stem."
          "</figcaption></figure><figure>"
        + (_chart(dbh, "distance from the track, m", "DBH error (SIC − true), cm", xlim=xlim,
                  zero=True) if any(s["points"] for s in dbh) else
           "<p>No DBH pairs (the SIC or the truth gives no DBH).</p>")
        + "<figcaption>Observed minus true diameter at breast height.</figcaption>"
          "</figure></div>")
    step = _nice(xlim[1], 7)
    bands = []
    lo = 0.0
    while lo < xlim[1] + 1e-9:
        hi = lo + step
        band = [r for r in rows if lo <= r["distance_to_track_m"] < hi]
        if band:
            m = [r for r in band if r["outcome"] in ("correct", "misclassified")]
            seen = [r for r in band if r["outcome"] != "missed_unseen"]
            pe = [r["match_distance_m"] for r in m if r["match_distance_m"] is not None]
            de = [r["observed_dbh_m"] - r["dbh_m"] for r in m
                  if r["observed_dbh_m"] is not None and r["dbh_m"] is not None]
            rp, rd = _rms(pe), _rms(de)
            bands.append(
                f"<tr><td>{lo:g}–{hi:g}</td><td>{len(band)}</td>"
                f"<td>{100 * len(seen) / len(band):.0f} %</td>"
                f"<td>{100 * len(m) / len(band):.0f} %</td>"
                f"<td>{_f(None if rp is None else 100 * rp, '{:.1f}')}</td>"
                f"<td>{_f(None if rd is None else 100 * rd, '{:.1f}')}</td>"
                f"<td>{_f(100 * sum(de) / len(de) if de else None, '{:+.1f}')}</td></tr>")
        lo = hi
    table = ("<table class=num><tr><th>from the track, m</th><th>trees</th><th>seen</th>"
             "<th>found</th><th>position RMSE, cm</th><th>DBH RMSE, cm</th>"
             "<th>DBH bias, cm</th></tr>" + "".join(bands) + "</table>")
    return charts + table


def _rms(v: list[float]) -> float | None:
    return math.sqrt(sum(e * e for e in v) / len(v)) if v else None


def _timeline(tl: list[dict[str, Any]], faults: list[dict[str, Any]],
              man: dict[str, Any]) -> str:
    if not tl:
        return "<p>No valid publication: no timeline.</p>"
    series = [
        {"name": "wc, all trees", "colour": "#0072B2", "line": True,
         "points": [(r["arrival_s"], r["wc_all"]) for r in tl if r["wc_all"] is not None]},
        {"name": "wc, seen trees", "colour": "#56B4E9", "line": True,
         "points": [(r["arrival_s"], r["wc_seen"]) for r in tl if r["wc_seen"] is not None]},
        {"name": "F1 × 100, all trees", "colour": "#009E73", "line": True,
         "points": [(r["arrival_s"], 100 * r["f1_all"]) for r in tl
                    if r.get("f1_all") is not None]},
    ]
    clock = man.get("clock") or {}
    lead, speed = float(clock.get("lead_s", 0.0)), float(clock.get("speed", 1.0)) or 1.0
    lanes: list[tuple[str, str, list[tuple[float, int]]]] = []
    palette = ["#D55E00", "#CC79A7", "#E69F00", "#0072B2", "#009E73", "#56B4E9"]
    by_kind: dict[str, list[float]] = {}
    for e in faults:
        by_kind.setdefault(str(e.get("kind", "fault")), []).append(
            lead + float(e.get("t_s", 0.0)) / speed)
    x_hi = max([r["arrival_s"] for r in tl] + [t for v in by_kind.values() for t in v])
    for k, (kind, ts) in enumerate(sorted(by_kind.items())):
        # one tick per 1/300 of the axis, with the count of events it stands for
        b = np.floor(np.asarray(ts) / max(x_hi, 1e-9) * 300)
        uniq, counts = np.unique(b, return_counts=True)
        lanes.append((kind, palette[k % len(palette)],
                      [(float(u) / 300 * x_hi, int(c)) for u, c in zip(uniq, counts, strict=True)]))
    chart = _chart(series, "seconds since the run started (publication arrival)",
                   "score, %", ylim=(0, 100), xlim=(0.0, x_hi * 1.02 or 1.0), lanes=lanes,
                   width=900, height=320)
    note = ("" if not lanes else
            f"<p>Faults below the chart, each at the run's lead of {lead:g} s plus its "
            f"simulation time / speed {speed:g} (hover a tick for its count).</p>")
    return chart + note


def _em_table(em: dict[str, Any] | None) -> str:
    if not em:
        return "<p>No evaluation matrix (the truth has no classes).</p>"
    m = em["matrix"]
    labels = em.get("labels", list(LABELS))
    top = max(1, max(max(r) for r in m))
    head = "".join(f"<th>{html.escape(c)}</th>" for c in labels)
    body = "".join(
        f"<tr><th>{html.escape(r)}</th>" + "".join(
            f'<td style="background:rgba(0,114,178,{0.08 + 0.7 * v / top:.2f})">{v}</td>'
            for v in m[i]) + "</tr>" for i, r in enumerate(labels))
    return f"<table class=em><tr><th>truth \\ SIC</th>{head}</tr>{body}</table>"


def _scores(score: dict[str, Any]) -> str:
    a, s = score.get("all_trees") or {}, score.get("seen_trees") or {}
    if not a:
        return "<p>Not scored.</p>"
    rows = "".join(f"<tr><td>{html.escape(label)}</td><td>{show_metric(fmt, a.get(key))}</td>"
                   f"<td>{show_metric(fmt, s.get(key))}</td></tr>" for key, label, fmt in ROWS)
    rows += (f"<tr><td>Ground-truth trees</td><td>{a.get('n_ground_truth')}</td>"
             f"<td>{s.get('n_ground_truth')}</td></tr>")
    bad = "".join(f"<li>{html.escape(p['file'])}: {html.escape(str(p['error']))}</li>"
                  for p in score.get("invalid_publications") or [])
    faults = score.get("faults")
    ftab = ""
    if faults is not None:
        frows = "".join(
            f"<tr><td>{html.escape(k)}</td><td>{v['count']}</td><td>{v['first_s']:.3f}</td>"
            f"<td>{v['last_s']:.3f}</td></tr>" for k, v in faults.items())
        ftab = ("<h3>Injected faults</h3><p>Every event is in <code>faults.jsonl</code>, "
                "with its time in seconds after the track start.</p><table class=num><tr>"
                "<th>fault</th><th>count</th><th>first, s</th><th>last, s</th></tr>"
                + (frows or "<tr><td colspan=4>none happened (rates too low or times beyond "
                   "the run)</td></tr>") + "</table>")
    return (
        "<p>“All trees” scores against every ground-truth stem; “seen trees” only against "
        "the stems the sensor returned at least one point from: the difference is what the "
        "sensor could not see, what remains is what the algorithm missed.</p>"
        "<table class=num><tr><th>metric</th><th>all trees</th><th>seen trees</th></tr>"
        + rows + "</table>" + ftab
        + '<h3>Evaluation matrices (rows truth, columns SIC)</h3><div class="charts">'
        + f"<div><h4>all trees</h4>{_em_table(a.get('em'))}</div>"
        + f"<div><h4>seen trees</h4>{_em_table(s.get('em'))}</div></div>"
        + f"<h3>Invalid publications</h3><ul>{bad or '<li>none</li>'}</ul>")


def _cell(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.6g}"
    if isinstance(v, list):
        return ", ".join(_cell(x) for x in v)
    if v is None:
        return "–"
    return str(v)


def _flat(d: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for k, v in d.items():
        if isinstance(v, dict):
            out += _flat(v, f"{prefix}{k}.")
        else:
            out.append((prefix + k, v))
    return out


def _figures(man: dict[str, Any], run: Path) -> str:
    """The manifest (and the sensor's visibility figures) as tables, one per part."""
    groups: dict[str, list[tuple[str, Any]]] = {"run": []}
    for k, v in man.items():
        if isinstance(v, dict):
            groups[k] = _flat(v)
        else:
            groups["run"].append((k, v))
    vis = run / "visibility.json"
    if vis.exists():
        try:
            doc = read_json(vis)
            groups["sensor (visibility.json)"] = [
                (k, v) for k, v in doc.items() if not isinstance(v, dict | list)]
        except InputError:
            pass
    out = []
    for name, rows in groups.items():
        if not rows:
            continue
        body = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(_cell(v))}</td></tr>"
                       for k, v in rows)
        out.append(f'<div><h4>{html.escape(name)}</h4><table class="kv">{body}</table></div>')
    return '<div class="figs">' + "".join(out) + "</div>"


_PAGE = """<!doctype html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<link rel="icon" href="data:,">
<title>{{title}}</title>
<style>{{css}}</style></head><body>
<header><h1>{{title}}</h1>{{head}}
<nav><a href="#map">Map</a><a href="#cloud">Cloud 3D</a><a href="#stems">Stems</a>
<a href="#errors">Errors by distance</a><a href="#timeline">Timeline</a>
<a href="#scores">Scores</a><a href="#figures">Run figures</a></nav></header>
<main>
<div class="views">
<section id="map"><h2>Map</h2>
<div class="layers">Layers:
<label><input type="checkbox" data-toggle="terrain" checked> terrain</label>
<label><input type="checkbox" data-toggle="cloud" checked> cloud (top view)</label>
<label><input type="checkbox" data-toggle="grid" checked> grid</label>
<label><input type="checkbox" data-toggle="track" checked> track</label>
<label><input type="checkbox" data-toggle="truth" checked> trees</label>
<label><input type="checkbox" data-toggle="sic" checked> SIC stems</label>
<button type="button" id="map-reset">reset view</button></div>
<div class="mapbox">{{map}}<div id="tip" hidden></div></div>
<p class="note">{{map_note}} Wheel to zoom, drag to pan, hover a tree for its facts, click to
pin them. Grey lines join a tree to its SIC stem.</p>
<div id="facts" class="facts"><p>Click a tree or a SIC stem on the map or in the table.</p></div>
</section>
<section id="cloud"><h2>The cloud as the sensor saw it</h2>
<div class="layers">Colour: <select id="cloud-colour"><option value="class">stems by id,
vegetation, ground</option><option value="height">height</option></select>
Point size: <select id="cloud-size"><option>1</option><option selected>2</option>
<option>3</option></select> <button type="button" id="cloud-reset">reset view</button></div>
<canvas id="cloud3d" width="640" height="560"></canvas>
<p class="note">{{cloud_note}} Drag to turn, wheel to zoom, shift-drag to pan.</p>
</section>
</div>
<section id="stems"><h2>Stems</h2>
<div class="layers">Show: <select id="stem-filter"><option value="">all</option></select>
<button type="button" id="csv">download CSV</button> <span id="stem-count"></span></div>
<div class="tablebox"><table id="stem-table" class="num sortable"><thead></thead><tbody>
</tbody></table></div>
<p class="note">Click a column to sort. “why” says why a tree was missed: not seen (no
return), merged with a neighbour (a SIC stem within the matching distance went to another
tree), few returns (under the tenth percentile of the returns of the trees the SIC found)
or seen, not found.</p>
</section>
<section id="errors"><h2>Errors against distance from the track</h2>{{errors}}</section>
<section id="timeline"><h2>Score timeline</h2>{{timeline}}</section>
<section id="scores"><h2>Scores</h2>{{scores}}</section>
<section id="figures"><h2>Run figures</h2>{{figures}}</section>
</main>
<script type="application/json" id="tcf-data">{{data}}</script>
<script>{{js}}</script>
</body></html>
"""
