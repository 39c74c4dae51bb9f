"""A soak run: the whole bench live for minutes at 2048x10 with the reference SIC as its own
process, watched for what only a long run shows: frames lost at the receiver, the pacing
error, and memory that grows.

The track is shortened to a stretch of the strip road driven back and forth (reverse gear,
no U-turn) so that after the first pass, the warm-up, the SIC has seen everything it will see:
from then on a healthy bench and SIC hold their memory flat. Resident memory (VmRSS) of the
bench process, its frame producer and the SIC is sampled every few seconds while the stream
runs; the growth is the median of the last three samples against the median of the first
three after the warm-up. The lidar pcap and the per-column poses are not kept (2048x10 sends
16 MB/s); everything else of a run directory is.
"""

from __future__ import annotations

import dataclasses
import math
import os
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from tcf_hil._io import ensure_dir, read_json, write_bytes_atomic, write_json_atomic
from tcf_hil.scenario import Scenario

if TYPE_CHECKING:
    from tcf_hil.run import Manifest

__all__ = ["SoakResult", "process_rss_kb", "run_soak", "soak_scenario"]

MAX_PASSES = 20  # the scenario's track.passes limit


def soak_scenario(scn: Scenario, seconds: float) -> tuple[Scenario, float]:
    """``scn`` with its track cut to a stretch driven back and forth for at least
    ``seconds``; returns it and the duration of the first pass (the warm-up), in seconds."""
    tr = scn.track
    x0, y0, h = tr.start_m
    x1, y1 = tr.end_m[:2]
    road = math.hypot(x1 - x0, y1 - y0)
    # at least four passes, and no more than the track allows
    length = min(road, max(tr.speed_m_s * seconds / 4.0,
                           tr.speed_m_s * seconds / (MAX_PASSES - 1) + 1.0, 5.0))
    leg_s = length / tr.speed_m_s + tr.stop_s
    passes = min(MAX_PASSES, math.ceil(seconds / leg_s) + 1)
    if passes * leg_s < seconds:
        raise ValueError(f"{seconds:g} s is longer than {MAX_PASSES} passes of the "
                         f"{road:.0f} m road at {tr.speed_m_s:g} m/s")
    ux, uy = (x1 - x0) / road, (y1 - y0) / road
    track = dataclasses.replace(tr, end_m=(x0 + ux * length, y0 + uy * length, h),
                                passes=passes, pass_offset_m=0.0, waypoints_m=())
    return dataclasses.replace(scn, track=track), length / tr.speed_m_s


def process_rss_kb(pid: int) -> int | None:
    """Resident memory of ``pid`` in kB (None when it has gone)."""
    try:
        with open(f"/proc/{pid}/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except OSError:
        return None
    return None


def _children(pid: int) -> list[int]:
    out: list[int] = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return out
    for t in tasks:
        try:
            with open(f"/proc/{pid}/task/{t}/children", encoding="ascii") as fh:
                out += [int(x) for x in fh.read().split()]
        except OSError:
            continue
    return out


def _label(pid: int, sic_pid: int | None) -> str:
    if pid == os.getpid():
        return "bench"
    if pid == sic_pid:
        return "sic"
    try:
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(
            errors="replace")
    except OSError:
        return "other"
    if "tcf_hil.sic" in cmd:
        return "sic"
    if "resource_tracker" in cmd:
        return "resource tracker"
    own = Path("/proc/self/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    return "frame producer" if cmd == own else "other"  # a fork of the bench


@dataclass
class RssTrace:
    """RSS samples per process role: (seconds since the stream started, kB)."""

    samples: dict[str, list[tuple[float, int]]] = field(default_factory=dict)

    def add(self, t_s: float, by_role: dict[str, int]) -> None:
        for role, kb in by_role.items():
            self.samples.setdefault(role, []).append((t_s, kb))

    def growth(self, warmup_s: float) -> dict[str, dict[str, Any]]:
        """Per role: kB at the end of the warm-up, at the end, the peak and the growth in %
        (medians of three samples, so one sample caught mid-allocation does not decide)."""
        out: dict[str, dict[str, Any]] = {}
        for role, s in self.samples.items():
            after = [kb for t, kb in s if t >= warmup_s]
            if len(after) < 2:
                continue
            k = min(3, len(after) // 2)
            base = sorted(after[:k])[k // 2]
            end = sorted(after[-k:])[k // 2]
            out[role] = {"rss_mb_after_warmup": round(base / 1024, 1),
                         "rss_mb_end": round(end / 1024, 1),
                         "rss_mb_peak": round(max(kb for _t, kb in s) / 1024, 1),
                         "growth_percent": round(100.0 * (end - base) / base, 2),
                         "samples": len(after)}
        return out


class _Sampler(threading.Thread):
    def __init__(self, period_s: float) -> None:
        super().__init__(name="soak-rss", daemon=True)
        self.period_s = period_s
        self.trace = RssTrace()
        self.sic_pid: int | None = None
        self.t0: float | None = None  # set when the stream starts
        self.stop = threading.Event()

    def sample(self) -> None:
        if self.t0 is None:
            return
        by_role: dict[str, int] = {}
        for pid in [os.getpid(), *_children(os.getpid())]:
            kb = process_rss_kb(pid)
            if kb is not None:
                role = _label(pid, self.sic_pid)
                by_role[role] = by_role.get(role, 0) + kb
        self.trace.add(time.monotonic() - self.t0, by_role)

    def run(self) -> None:
        while not self.stop.wait(self.period_s):
            self.sample()


@dataclass
class SoakResult:
    out: Path
    doc: dict[str, Any]
    ok: bool


def run_soak(scn: Scenario, out: Path, *, minutes: float = 10.0, mode: str = "2048x10",
             preset: str = "field", sample_s: float = 2.0, seed: int | None = None,
             max_growth_percent: float = 5.0, announce: Callable[[str], None] = lambda s: None,
             progress: Callable[[int, int], None] | None = None,
             stop: threading.Event | None = None,
             watch: Callable[[Any], None] | None = None) -> SoakResult:
    """Run the soak (see the module docstring) into ``out``; writes ``soak.json`` and
    ``soak.md`` beside the run's files. ``ok``: the run completed with no frame lost at the
    receiver and every process's memory growth under ``max_growth_percent``. ``watch``: the
    run's live figures (:class:`tcf_hil.run.RunSession`)."""
    from tcf_hil.run import run_bridge, sic_reference_command

    seconds = minutes * 60.0
    soak, warmup_s = soak_scenario(scn, seconds)
    warmup_s += soak.track.stop_s  # the first pass and the standstill before reversing
    out = ensure_dir(out)
    sampler = _Sampler(sample_s)
    sampler.start()
    stream_end: list[float] = []

    def on_start(manifest: Manifest) -> None:
        sampler.sic_pid = manifest.sic.pid if manifest.sic is not None else None
        sampler.t0 = time.monotonic() + float((manifest.clock or {}).get("lead_s", 0.0))

    def step(done: int, total: int) -> None:
        if done >= total and not stream_end:
            stream_end.append(time.monotonic())
            sampler.stop.set()  # the final stem pass of the SIC is not the steady state
        if progress is not None:
            progress(done, total)

    stretch = math.dist(soak.track.start_m[:2], soak.track.end_m[:2])
    announce(f"soak: {scn.name} {mode}, {minutes:g} min, a {stretch:.0f} m stretch driven "
             f"{soak.track.passes} times (warm-up: the first {warmup_s:.0f} s)")
    try:
        r = run_bridge(soak, sic_reference_command(preset), out, mode=mode, seed=seed,
                       duration_s=seconds, record_lidar=False, on_start=on_start,
                       progress=step, announce=announce, stop=stop, watch=watch)
    finally:
        sampler.stop.set()
        sampler.join(timeout=5.0)
    lid = r.manifest.lidar or {}
    sic = _last_sic_section(out)
    map_points = _map_points(out, warmup_s * soak_frequency(mode))
    mem = sampler.trace.growth(warmup_s)
    frames_sent = int(lid.get("frames_sent", 0))
    lost = int(sic.get("frames_lost", 0))
    doc: dict[str, Any] = {
        "scenario": scn.name, "mode": mode, "preset": preset, "minutes": minutes,
        "status": r.status, "message": r.message,
        "track": {"stretch_m": round(stretch, 1),
                  "passes": soak.track.passes, "warmup_s": round(warmup_s, 1)},
        "frames_sent": frames_sent, "frames_mapped_by_sic": int(sic.get("frames", 0)),
        "frames_lost_at_receiver": lost,
        "frames_dropped_by_sic": int(sic.get("frames_dropped", 0)),
        "frames_without_pose": int(sic.get("frames_without_pose", 0)),
        "pacing_us_p50": (lid.get("pacing_us_p50_p99") or [0, 0])[0],
        "pacing_us_p99": (lid.get("pacing_us_p50_p99") or [0, 0])[1],
        "sender_cpu_share": lid.get("sender_cpu_share"),
        "sic_frame_cost": sic.get("frame_cost", {}),
        "memory": mem, "max_growth_percent": max_growth_percent,
        "sic_map_points_after_warmup_end": map_points,
        "wc_all": r.scores.all.metrics["evaluation_score_percent"] if r.scores else None,
        "f1_all": r.scores.all.metrics["f1"] if r.scores else None,
    }
    # the aim is the bench's: the SIC under test is reported, not judged (its map fills as
    # it sees far stems from ever more positions, up to its own bound)
    bench = {k: v for k, v in mem.items() if k != "sic"}
    worst = max((m["growth_percent"] for m in bench.values()), default=0.0)
    ok = (r.status == "complete" and lost == 0 and bool(bench)
          and worst < max_growth_percent)
    doc["ok"] = ok
    doc["verdict"] = _verdict(doc, worst)
    write_json_atomic(out / "soak.json", doc)
    write_bytes_atomic(out / "soak.md", soak_markdown(doc).encode())
    return SoakResult(out, doc, ok)


def soak_frequency(mode: str) -> int:
    return int(mode.split("x")[1])


def _publications(out: Path) -> list[dict[str, Any]]:
    """The SIC's valid publications in order (their documents)."""
    import json

    index = out / "sic" / "index.ndjson"
    if not index.exists():
        return []
    docs = []
    for x in index.read_text(encoding="utf-8").splitlines():
        if not x.strip():
            continue
        try:
            doc = read_json(out / "sic" / json.loads(x)["file"])
        except Exception:  # an invalid publication
            continue
        if isinstance(doc, dict) and isinstance(doc.get("sic"), dict):
            docs.append(doc)
    return docs


def _map_points(out: Path, warmup_frames: float) -> list[int]:
    """The SIC's map points at the first publication after the warm-up and at the last one
    before its final stem pass (empty when it publishes no such counter)."""
    docs = [d for d in _publications(out) if not d["sic"].get("final")
            and isinstance(d["sic"].get("map_points"), int)]
    after = [d for d in docs if d["sic"].get("frames", 0) >= warmup_frames]
    if len(after) < 2:
        return []
    return [after[0]["sic"]["map_points"], after[-2]["sic"]["map_points"]]


def _last_sic_section(out: Path) -> dict[str, Any]:
    """The ``sic`` section of the SIC's last valid publication (its own counters)."""
    docs = _publications(out)
    return dict(docs[-1]["sic"]) if docs else {}


def _verdict(doc: dict[str, Any], worst: float) -> str:
    parts = []
    if doc["status"] != "complete":
        parts.append(f"run {doc['status']}")
    parts.append("no frame lost" if doc["frames_lost_at_receiver"] == 0 else
                 f"{doc['frames_lost_at_receiver']} frames lost at the receiver")
    if any(k != "sic" for k in doc["memory"]):
        parts.append(f"bench memory growth at most {worst:.1f} % "
                     f"({'within' if worst < doc['max_growth_percent'] else 'above'} "
                     f"{doc['max_growth_percent']:g} %)")
    else:
        parts.append("no memory samples after the warm-up (run too short)")
    return "; ".join(parts)


def soak_markdown(doc: dict[str, Any]) -> str:
    lines = [f"# Soak: {doc['scenario']} {doc['mode']}, {doc['minutes']:g} min",
             "", f"**{'PASS' if doc['ok'] else 'FAIL'}**: {doc['verdict']}", "",
             "| figure | value |", "|---|---|"]
    for key, label in (("frames_sent", "frames sent"),
                       ("frames_mapped_by_sic", "frames the SIC mapped"),
                       ("frames_lost_at_receiver", "frames lost at the receiver"),
                       ("frames_dropped_by_sic", "frames the SIC dropped (behind)"),
                       ("frames_without_pose", "frames without a pose"),
                       ("pacing_us_p50", "pacing error p50, us"),
                       ("pacing_us_p99", "pacing error p99, us"),
                       ("sender_cpu_share", "pacing loop, share of a core"),
                       ("wc_all", "SIC wc (all trees), %"), ("f1_all", "SIC F1")):
        v = doc.get(key)
        lines.append(f"| {label} | {v:.3g} |" if isinstance(v, float) else f"| {label} | {v} |")
    lines += ["", f"Track: a {doc['track']['stretch_m']} m stretch, {doc['track']['passes']} "
              f"passes; warm-up {doc['track']['warmup_s']} s.", "",
              "| process | RSS after warm-up, MB | RSS at the end, MB | peak, MB | growth, % |",
              "|---|---|---|---|---|"]
    for role, m in sorted(doc["memory"].items()):
        lines.append(f"| {role} | {m['rss_mb_after_warmup']} | {m['rss_mb_end']} | "
                     f"{m['rss_mb_peak']} | {m['growth_percent']} |")
    mp = doc.get("sic_map_points_after_warmup_end") or []
    lines += ["", "The aim (growth under the limit) is the bench's: bench, frame producer and "
              "resource tracker. The SIC under test is reported, not judged"
              + (f"; its map held {mp[0]:,} points after the warm-up and {mp[1]:,} at the end "
                 "(it fills as far stems are seen from more positions, up to its own bound)."
                 if len(mp) == 2 else ".")]
    return "\n".join(lines) + "\n"
