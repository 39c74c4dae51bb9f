"""Matplotlib figures (headless, deterministic PNG bytes: no timestamps or version stamps)."""

from __future__ import annotations

import io
from collections.abc import Sequence
from typing import Any

import numpy as np

CLASS_COLOURS = {"S": "#2a9d3c", "C": "#e08a1e", "X": "#c0392b"}


def pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def figure_png(fig: Any) -> bytes:
    """Render and close ``fig``; PNG metadata stripped so equal figures give equal bytes."""
    plt = pyplot()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, metadata={"Software": None})
    plt.close(fig)
    return buf.getvalue()


def forest_map(xy: np.ndarray, classes: Sequence[str], dbh: np.ndarray, title: str,
               bounds: tuple[float, float, float, float],
               track: tuple[Sequence[float], Sequence[float]] | None = None,
               terrain: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None) -> bytes:
    """Top view of the stems coloured by class (marker area grows with DBH)."""
    plt = pyplot()
    w = bounds[2] - bounds[0]
    h = bounds[3] - bounds[1]
    fig, ax = plt.subplots(figsize=(7.5, max(3.0, min(12.0, 7.0 * h / max(w, 1e-9)))))
    if terrain is not None:
        xs, ys, z = terrain
        cs = ax.contourf(xs, ys, z, levels=12, cmap="Greys", alpha=0.35)
        fig.colorbar(cs, ax=ax, label="ground height (m)", shrink=0.8)
    cls = np.asarray(classes)
    for c, colour in CLASS_COLOURS.items():
        m = cls == c
        if m.any():
            ax.scatter(xy[m, 0], xy[m, 1], s=np.clip(dbh[m] * 60.0, 4.0, 60.0), c=colour,
                       label=f"{c} ({int(m.sum())})", edgecolors="none")
    if track is not None:
        (x0, y0, *_), (x1, y1, *_) = track
        ax.plot([x0, x1], [y0, y1], "--", color="#1f4e9a", lw=1.2, label="sensor track")
        ax.annotate("", (x1, y1), (x0, y0), arrowprops={"arrowstyle": "->", "color": "#1f4e9a"})
    ax.set_xlim(bounds[0], bounds[2])
    ax.set_ylim(bounds[1], bounds[3])
    ax.set_aspect("equal")
    ax.set_xlabel("x (m, east)")
    ax.set_ylabel("y (m, north)")
    ax.set_title(title)
    ax.legend(loc="upper right", fontsize=8, framealpha=0.85)
    fig.tight_layout()
    return figure_png(fig)


def em_heatmap(em: np.ndarray, labels: Sequence[str], title: str) -> bytes:
    """Annotated evaluation-matrix heatmap (rows ground truth, columns observed)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(4.8, 4.2))
    im = ax.imshow(em, cmap="viridis")
    ax.set_xticks(range(len(labels)), labels)
    ax.set_yticks(range(len(labels)), labels)
    ax.set_xlabel("observed class")
    ax.set_ylabel("ground-truth class")
    vmax = float(np.max(em)) if em.size else 0.0
    for i in range(em.shape[0]):
        for j in range(em.shape[1]):
            v = em[i, j]
            txt = f"{v:g}"
            ax.text(j, i, txt, ha="center", va="center",
                    color="black" if vmax and v > 0.6 * vmax else "white", fontsize=10)
    ax.set_title(title, fontsize=10)
    fig.colorbar(im, ax=ax, shrink=0.8)
    fig.tight_layout()
    return figure_png(fig)


def matched_positions(gt_xy: np.ndarray, obs_xy: np.ndarray, pairs: np.ndarray,
                      title: str) -> bytes:
    """Ground truth in blue, observed in red, matched pairs joined (the paper's Table 5)."""
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 6.5))
    if len(gt_xy):
        ax.scatter(gt_xy[:, 0], gt_xy[:, 1], s=14, c="#1f5fbf",
                   label=f"ground truth ({len(gt_xy)})")
    if len(obs_xy):
        ax.scatter(obs_xy[:, 0], obs_xy[:, 1], s=6, c="#d62728", label=f"observed ({len(obs_xy)})")
    if len(pairs):
        from matplotlib.collections import LineCollection

        segs = np.stack([gt_xy[pairs[:, 0]], obs_xy[pairs[:, 1]]], axis=1)
        ax.add_collection(LineCollection(list(segs), colors="#555555", linewidths=0.6))
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_title(title, fontsize=10)
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return figure_png(fig)
