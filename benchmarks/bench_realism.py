#!/usr/bin/env python3
"""Realism statistics of an Ouster recording (pcap + metadata JSON, or an OSF).

Reads up to --frames lidar frames with ouster-sdk, destaggers them, and
reports numbers that can be compared between a real sensor and an emulator.
Only the first return is used (dual-return profiles). Ranges come from the
RANGE field; pixels in invalid columns (column status bit 0 clear, e.g. an
azimuth window or a partial first frame) are left out everywhere. RANGE is
whole mm (8 mm steps in the RNG15 low-data profile), so MAD-based sigmas of a
few mm are quantised. Fields an OSF did not store come out null.

identity      product line, firmware, mode (columns x Hz), UDP lidar profile,
              beams, frames read / complete.
returns       share of pixels with RANGE > 0, overall and for beams pointing
              below (beam altitude < 0) or at/above the horizon of the SENSOR
              frame (not gravity: a tilted mount moves that horizon).
plane_noise   range noise on locally planar surfaces. For each pixel whose 3x3
              neighbourhood (beam x column, destaggered) all returned, a plane
              is fitted (PCA) to the XYZ points of the 8 neighbours. The patch
              is kept when their surface variation l0/(l0+l1+l2) < --max-curv
              and the centre's ray meets the plane at |cos(incidence)| >= 0.2.
              The centre's residual is taken ALONG ITS RAY, so it is in range
              units. The centre is left out of the fit, so the planarity gate
              does not pick quiet centres; sigma = 1.4826*MAD/sqrt(1+1/8) (the
              1/8 is the fitted plane's own error) in mm, by range bin and by
              SIGNAL bin (the SIGNAL view is the less scene-dependent one).
frame_diff    same pixel in consecutive frames, returns in both, |dr| < 0.5 m:
              sigma = 1.4826*MAD(dr)/sqrt(2) in mm by range and SIGNAL bin.
              Range noise only if sensor and scene were static: `static` is
              true when, on beams within 10 deg of the horizon (walls, trunks:
              flat ground keeps its range under translation), the median dr of
              each of 8 azimuth sectors is within 3 mm.
fields        p5/p25/p50/p75/p95 of SIGNAL, NEAR_IR and REFLECTIVITY over
              returning pixels (absent fields are null); SIGNAL also by range.
mixed_pixels  destaggered neighbour triples (left, centre, right), and along
              the vertical (up, centre, down), whose outer ranges both returned
              and differ by > 1 m (an edge). gap_share: of those with a centre
              return, the share whose centre lies strictly inside the gap with
              > 0.25 m to both sides (a point floating behind the edge);
              centre_dropout_share: edge triples without a centre return.
              *_step: only edges with flat sides (the next pixel outward on
              each side within 0.25 m): far ground seen by successive beams is
              a ramp, not an edge (ranges grow by metres per beam), and would
              otherwise count as "in the gap", most of all along the vertical.
"""
from __future__ import annotations

import argparse
import itertools
import json
import sys

import numpy as np
from ouster.sdk import core, open_source

RANGE_BINS = (0.0, 5.0, 10.0, 20.0, np.inf)        # m
SIGNAL_BINS = (0, 30, 100, 300, 1000, np.inf)      # SIGNAL counts
PCTS = (5, 25, 50, 75, 95)
MIN_N = 30                                         # fewer samples: sigma null
OFFS = [(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1) if dy or dx]


def rsigma(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def bins(edges, unit: str):
    for lo, hi in itertools.pairwise(edges):
        yield (f"{lo:g}-{hi:g}{unit}" if np.isfinite(hi) else f"{lo:g}+{unit}"), lo, hi


def binned(values, key, edges, unit, scale):
    """Robust sigma of `values` (m) in mm * scale, per bin of `key`."""
    out = {}
    for name, lo, hi in bins(edges, unit):
        sel = (key >= lo) & (key < hi)
        n = int(sel.sum())
        out[name] = {"n": n, "sigma_mm": round(rsigma(values[sel]) * 1000 * scale, 1)
                     if n >= MIN_N else None}
    return out


def pcts(x: np.ndarray):
    return None if x.size < MIN_N else {
        f"p{p}": round(float(v), 1) for p, v in zip(PCTS, np.percentile(x, PCTS), strict=True)}


def plane_residuals(p: np.ndarray, r: np.ndarray, max_curv: float):
    """Leave-one-out range residual (m) of centres of planar 3x3 patches."""
    H, W = r.shape
    ok = r > 0
    allok = ok[1:-1, 1:-1].copy()
    for dy, dx in OFFS:
        allok &= ok[1 + dy:H - 1 + dy, 1 + dx:W - 1 + dx]
    nb = np.stack([p[1 + dy:H - 1 + dy, 1 + dx:W - 1 + dx][allok] for dy, dx in OFFS], 1)
    pc = p[1:-1, 1:-1][allok]
    mu = nb.mean(axis=1)
    d = nb - mu[:, None]
    w, v = np.linalg.eigh(np.einsum("nki,nkj->nij", d, d) / 8.0)
    normal = v[:, :, 0]                                   # smallest eigenvalue
    curv = w[:, 0] / np.maximum(w.sum(axis=1), 1e-15)
    u = pc / np.linalg.norm(pc, axis=1, keepdims=True)
    ndu = np.einsum("ni,ni->n", normal, u)
    keep = (curv < max_curv) & (np.abs(ndu) >= 0.2)
    resid = np.einsum("ni,ni->n", normal, pc - mu)[keep] / ndu[keep]
    return resid, allok, keep, int(allok.sum())


def mixed(r: np.ndarray) -> np.ndarray:
    """Counts along axis 1: [edges, with centre, in gap] for all and for step edges."""
    a2, a, c, b, b2 = (r[:, i:r.shape[1] - 4 + i] for i in range(5))
    edge = (a > 0) & (b > 0) & (np.abs(a - b) > 1.0)
    step = edge & (np.abs(a2 - a) < 0.25) & (np.abs(b2 - b) < 0.25)
    inside = (c > np.minimum(a, b) + 0.25) & (c < np.maximum(a, b) - 0.25)
    return np.array([m.sum() for e in (edge, step) for m in (e, e & (c > 0), e & inside)])


def identity(info, n_read: int, n_complete: int) -> dict:
    fmt = info.format
    mode = str(info.config.lidar_mode)
    if not mode or mode in ("None", "UNSPECIFIED"):
        mode = f"{fmt.columns_per_frame}x{fmt.fps}"
    return {"product": info.prod_line, "firmware": info.fw_rev, "image": info.image_rev,
            "serial": str(info.sn), "mode": mode, "profile": str(fmt.udp_profile_lidar),
            "beams": int(fmt.pixels_per_column), "columns": int(fmt.columns_per_frame),
            "frames_read": n_read, "frames_complete": n_complete}


def analyse(args) -> dict:
    src = open_source(args.pcap, **({"meta": [args.meta]} if args.meta else {}))
    info = src.sensor_info[args.sensor_idx]
    lut = core.XYZLut(info)
    alt = np.asarray(info.beam_altitude_angles)
    below, level = alt < 0, np.abs(alt) <= 10.0
    acc: dict[str, list] = {k: [] for k in ("res", "res_r", "res_s", "dr", "dr_r", "dr_s",
                                           "r", "SIGNAL", "NEAR_IR", "REFLECTIVITY")}
    hits = np.zeros((2, 2), np.int64)                      # [below, above] x [valid, hit]
    mix = np.zeros((2, 6), np.int64)                       # horizontal, vertical
    patches = np.zeros(2, np.int64)                        # candidates, planar
    sector_med: list[float] = []
    prev, n_read, n_complete = None, 0, 0
    for fs in src:
        sc = fs[args.sensor_idx] if args.sensor_idx < len(fs) else None
        if sc is None:
            continue
        if n_read >= args.skip + args.frames:
            break
        n_read += 1
        if n_read <= args.skip:
            continue
        n_complete += int(sc.complete())
        colok = (np.asarray(sc.status) & 1).astype(bool)
        raw = np.where(colok[None, :], sc.field("RANGE"), 0).astype(np.uint32)
        for k, rows in enumerate((below, ~below)):
            hits[k] += (rows.sum() * colok.sum(), (raw[rows] > 0).sum())
        r = core.destagger(info, raw).astype(np.float64) / 1000.0
        p = core.destagger(info, np.ascontiguousarray(lut(raw)))
        f = {n: core.destagger(info, np.ascontiguousarray(sc.field(n))).astype(np.float64)
             for n in ("SIGNAL", "NEAR_IR", "REFLECTIVITY") if sc.has_field(n)}
        sig = f.get("SIGNAL", np.full(r.shape, np.nan))
        ret = r > 0
        acc["r"].append(r[ret])
        for n, img in f.items():
            acc[n].append(img[ret])
        res, allok, keep, ncand = plane_residuals(p, r, args.max_curv)
        patches += (ncand, keep.sum())
        for k, v in zip(("res", "res_r", "res_s"), (res, r, sig), strict=True):
            acc[k].append(v if k == "res" else v[1:-1, 1:-1][allok][keep])
        mix += (mixed(r), mixed(np.ascontiguousarray(r.T)))
        if prev is not None and prev.shape == r.shape:
            dr = r - prev
            sel = (prev > 0) & ret & (np.abs(dr) < 0.5)
            for k, v in zip(("dr", "dr_r", "dr_s"), (dr, r, sig), strict=True):
                acc[k].append(v[sel])
            sector = np.arange(r.shape[1]) * 8 // r.shape[1]
            for k in range(8):
                m = sel[level][:, sector == k]
                if m.sum() >= MIN_N:
                    sector_med.append(float(np.median(dr[level][:, sector == k][m])))
        prev = r
    cat = {k: (np.concatenate(v) if v else np.zeros(0)) for k, v in acc.items()}
    share = hits[:, 1] / np.maximum(hits[:, 0], 1)
    loo = 1 / np.sqrt(9 / 8)
    out = {"file": args.pcap, "identity": identity(info, n_read - args.skip, n_complete),
           "returns": {"all": round(float(hits[:, 1].sum() / max(hits[:, 0].sum(), 1)), 4),
                       "below_horizon": round(float(share[0]), 4),
                       "above_horizon": round(float(share[1]), 4),
                       "beams_below": int(below.sum()), "beams_above": int((~below).sum())},
           "plane_noise": {"candidates": int(patches[0]), "planar": int(patches[1]),
                           "max_curv": args.max_curv,
                           "by_range": binned(cat["res"], cat["res_r"], RANGE_BINS, "m", loo),
                           "by_signal": binned(cat["res"], cat["res_s"], SIGNAL_BINS, "", loo)},
           "frame_diff": None}
    if cat["res"].size >= MIN_N:
        out["plane_noise"]["all_sigma_mm"] = round(rsigma(cat["res"]) * 1000 * loo, 1)
    if sector_med:
        worst = max(abs(m) for m in sector_med)
        out["frame_diff"] = {
            "pairs": n_read - args.skip - 1, "n": int(cat["dr"].size),
            "max_sector_median_mm": round(worst * 1000, 1), "static": bool(worst < 0.003),
            "by_range": binned(cat["dr"], cat["dr_r"], RANGE_BINS, "m", 1 / np.sqrt(2)),
            "by_signal": binned(cat["dr"], cat["dr_s"], SIGNAL_BINS, "", 1 / np.sqrt(2))}
    out["fields"] = {n: pcts(cat[n]) for n in ("SIGNAL", "NEAR_IR", "REFLECTIVITY")}
    if cat["SIGNAL"].size:
        out["fields"]["SIGNAL_by_range"] = {
            name: pcts(cat["SIGNAL"][(cat["r"] >= lo) & (cat["r"] < hi)])
            for name, lo, hi in bins(RANGE_BINS, "m")}
    out["mixed_pixels"] = {
        f"{name}{kind}": {"edge_triples": int(m[0]), "with_centre": int(m[1]),
                          "gap_share": round(float(m[2] / max(m[1], 1)), 4),
                          "centre_dropout_share": round(float(1 - m[1] / max(m[0], 1)), 4)}
        for name, row in zip(("horizontal", "vertical"), mix, strict=True)
        for kind, m in (("", row[:3]), ("_step", row[3:]))}
    return out


def show(d, prefix: str = "") -> None:
    for k, v in d.items():
        if isinstance(v, dict):
            show(v, f"{prefix}{k}.")
        else:
            print(f"{prefix}{k}: {v}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        epilog="examples:\n"
               "  bench_realism.py rec.pcap --meta rec.json --frames 10\n"
               "  bench_realism.py out/lidar.pcap --meta out/metadata.json --json s.json\n"
               "  bench_realism.py rec.osf            (OSF carries its metadata)")
    ap.add_argument("pcap", help="recording: .pcap (with --meta) or .osf")
    ap.add_argument("--meta", help="metadata JSON of the pcap (sensor_info); "
                    "without it ouster-sdk looks for one next to the pcap")
    ap.add_argument("--frames", type=int, default=10, help="frames to analyse (default 10)")
    ap.add_argument("--skip", type=int, default=0, help="frames to skip first (default 0)")
    ap.add_argument("--sensor-idx", type=int, default=0,
                    help="sensor index in multi-sensor recordings (default 0)")
    ap.add_argument("--max-curv", type=float, default=0.05,
                    help="planarity gate: max surface variation l0/sum(l) of the "
                         "8 neighbours (default 0.05; 1/3 = isotropic blob)")
    ap.add_argument("--json", metavar="OUT", help="also write the statistics as JSON")
    args = ap.parse_args(argv)
    show(stats := analyse(args))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(stats, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
