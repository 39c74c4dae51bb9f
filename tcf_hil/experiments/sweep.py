"""Run a grid of cells on Dask (a LocalCluster, or a scheduler's address) or inline.

Each cell is an independent task. Its record lands in ``OUT/cells/<cell id>/cell.json`` the
moment it finishes, with a hash of its spec, so a rerun skips every cell already done with
the same spec (a failed cell is tried again). ``OUT/results.csv`` is rewritten after every
cell, always through a temporary name: this grid's cells in grid order, then every other
finished cell of ``OUT`` (a sweep extended by seeds or presets keeps one table).
"""

from __future__ import annotations

import contextlib
import csv
import hashlib
import io
import itertools
import json
import logging
import math
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from tcf_hil._io import ensure_dir, read_json, write_bytes_atomic, write_json_atomic
from tcf_hil.experiments.cells import COLUMN_NAMES, SAMPLED, Cell, CellResult, run_cell

Event = Callable[[str, Cell, dict[str, Any] | None], None]
"""on_event(kind, cell, row): kind is 'skipped', 'done' or 'failed' (``row``: the cell's), or
'progress' while a reference cell runs (``row``: ``{"frames": done, "total": frames}``, at
most twice a second; from a Dask worker through the scheduler's event log)."""

PROGRESS_TOPIC = "tcf-hil-cell-progress"
_PROGRESS_EVERY_S = 0.5


def _throttled(send: Callable[[dict[str, Any]], None]) -> Callable[[int, int], None]:
    """A cell's ``progress(done, total)`` that passes on at most one report per
    ``_PROGRESS_EVERY_S`` (and the last)."""
    last = [-_PROGRESS_EVERY_S]

    def progress(done: int, total: int) -> None:
        now = time.monotonic()
        if now - last[0] >= _PROGRESS_EVERY_S or done >= total:
            last[0] = now
            with contextlib.suppress(Exception):  # a display never fails a cell
                send({"frames": done, "total": total})
    return progress


def run_cell_reporting(cell: Cell, out_dir: str | None = None) -> CellResult:
    """:func:`run_cell` on a Dask worker, its frames reported to the client as events on
    :data:`PROGRESS_TOPIC` (no worker: no reports)."""
    try:
        from dask.distributed import get_worker

        worker = get_worker()
    except (ImportError, ValueError):
        return run_cell(cell, out_dir)
    return run_cell(cell, out_dir, _throttled(
        lambda msg: worker.log_event(PROGRESS_TOPIC, {"cell": cell.id, **msg})))


def spec_hash(cell: Cell) -> str:
    return hashlib.sha256(json.dumps(asdict(cell), sort_keys=True).encode()).hexdigest()[:16]


def cell_dir(out: Path, cell: Cell) -> Path:
    return out / "cells" / cell.id


def finished(out: Path, cell: Cell) -> dict[str, Any] | None:
    """The record of a cell already done with this very spec, else None."""
    p = cell_dir(out, cell) / "cell.json"
    try:
        rec = read_json(p)
    except Exception:  # missing or damaged: run it again
        return None
    if rec.get("spec") != spec_hash(cell) or rec.get("row", {}).get("status") != "ok":
        return None
    return rec


@dataclass
class SweepOutcome:
    records: list[dict[str, Any]]  # this grid in order, then other finished cells of OUT
    ran: int = 0
    skipped: int = 0
    failed: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0

    @property
    def rows(self) -> list[dict[str, Any]]:
        return [r["row"] for r in self.records]


def write_results_csv(path: Path, rows: Sequence[dict[str, Any]]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(COLUMN_NAMES), lineterminator="\n",
                       extrasaction="ignore")
    w.writeheader()
    for r in rows:
        w.writerow({k: _csv_value(r.get(k, "")) for k in COLUMN_NAMES})
    write_bytes_atomic(path, buf.getvalue().encode())


def _csv_value(v: Any) -> Any:
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


def _store(out: Path, cell: Cell, res: CellResult) -> dict[str, Any]:
    d = ensure_dir(cell_dir(out, cell))
    rec = {"spec": spec_hash(cell), "row": res.row,
           **{k: v for k, v in res.artifacts.items() if k.startswith("em_")}}
    for name in ("forest.json", "score.json"):
        if name in res.artifacts:
            write_json_atomic(d / name, res.artifacts[name])
    if res.row["status"] == "ok":
        write_json_atomic(d / "cell.json", rec)
        (d / "failed.json").unlink(missing_ok=True)
    else:
        write_json_atomic(d / "failed.json", {"row": res.row,
                                              "traceback": res.artifacts.get("traceback")})
    return rec


def parse_executor(spec: str) -> tuple[str, str | None]:
    """``local`` | ``inline`` | ``dask://HOST:PORT`` (or ``tcp://HOST:PORT``)."""
    s = spec.strip()
    if s in ("local", "inline"):
        return s, None
    for scheme in ("dask://", "tcp://"):
        if s.startswith(scheme) and ":" in s[len(scheme):]:
            return "dask", "tcp://" + s[len(scheme):]
    raise ValueError(f"--executor {spec!r}: expected local, inline or dask://HOST:PORT")


def _worker_env(workers: int) -> dict[str, str]:
    """A local worker's environment: its share of this machine's CPUs for the ray casts
    (``TCF_HIL_RAY_THREADS``, unless set here already). Each worker runs one cell at a
    time; casting over every CPU in each of them costs more than it gains (two workers on
    2 cores, a natural stand's cell: 76 s with two threads each, 71 s with one)."""
    from tcf_hil.world.scene import (
        default_threads,  # this machine's CPUs, unless the variable is set
    )

    if os.environ.get("TCF_HIL_RAY_THREADS"):
        return {}
    return {"TCF_HIL_RAY_THREADS": str(max(1, default_threads() // max(1, workers)))}


def estimated_cost(c: Cell) -> float:
    """A cell's work, roughly and for ordering only: the columns it casts (track length by
    speed, frames a second, columns a frame, passes) times the stems, four times over in a
    natural stand (branches, foliage, understory: 3-4x a paper forest's cell of the same
    stems here). A local sweep starts the costliest cells first, so that a long cell does
    not start last while the other workers idle."""
    scn = c.scenario()
    if c.mode == SAMPLED:
        return float(scn.stems.count)
    cols, hz = (int(v) for v in c.mode.split("x"))
    tr = scn.track
    pts = [tr.start_m[:2], *tr.waypoints_m, tr.end_m[:2]]
    length = sum(math.dist(a, b) for a, b in itertools.pairwise(pts))
    natural = 4.0 if scn.stand.kind == "natural" else 1.0
    seconds = length / tr.speed_m_s * tr.passes
    return seconds * hz * cols * (scn.stems.count + 10) * natural


def run_sweep(cells: Sequence[Cell], out: str | Path, *, executor: str = "local",
              workers: int | None = None, on_event: Event | None = None) -> SweepOutcome:
    """Run every cell not yet done; returns all records in grid order."""
    out = ensure_dir(out)
    ids = [c.id for c in cells]
    if len(set(ids)) != len(ids):
        raise ValueError("two cells of the grid share an id")
    kind, address = parse_executor(executor)
    say = on_event or (lambda *_a: None)
    t0 = time.perf_counter()
    records: dict[str, dict[str, Any]] = {}
    todo: list[Cell] = []
    for c in cells:
        rec = finished(out, c)
        if rec is not None:
            records[c.id] = rec
            say("skipped", c, rec["row"])
        else:
            todo.append(c)
    outcome = SweepOutcome([], skipped=len(records))
    others = _other_records(out, set(ids))

    def all_rows() -> list[dict[str, Any]]:
        return [records[i]["row"] for i in ids if i in records] + [r["row"] for r in others]

    def land(c: Cell, res: CellResult) -> None:
        rec = _store(out, c, res)
        records[c.id] = rec
        outcome.ran += 1
        if res.row["status"] != "ok":
            outcome.failed.append(res.row)
        write_results_csv(out / "results.csv", all_rows())
        say("done" if res.row["status"] == "ok" else "failed", c, res.row)

    def out_dir(c: Cell) -> str | None:
        return None if c.sic == "reference" else str(cell_dir(out, c).resolve())

    if todo and kind == "inline":
        for c in todo:
            land(c, run_cell(c, out_dir(c), _throttled(
                lambda msg, c=c: say("progress", c, msg))))  # type: ignore[misc]
    elif todo:
        from dask.distributed import Client, LocalCluster, as_completed

        cluster = None
        if kind == "local":
            n = workers or 2
            cluster = LocalCluster(n_workers=n, threads_per_worker=1,
                                   processes=True, dashboard_address=None,
                                   silence_logs=logging.ERROR, env=_worker_env(n))
            client = Client(cluster)
        else:
            client = Client(address, timeout="10s")
        by_id = {c.id: c for c in todo}

        def reported(event: Any) -> None:  # (time, message), on the client's event loop
            msg = dict(event[1])
            c = by_id.get(msg.pop("cell", None))
            if c is not None:
                say("progress", c, msg)

        try:
            client.subscribe_topic(PROGRESS_TOPIC, reported)
            # the costliest first (submitted first, and Dask runs the higher priority
            # first among those waiting): the last cells to start are short ones
            order = sorted(todo, key=estimated_cost, reverse=True)
            futures = {client.submit(run_cell_reporting, c, out_dir(c), pure=False,
                                     priority=len(order) - r,
                                     key=f"tcf-cell-{c.id}-{time.time_ns()}"): c
                       for r, c in enumerate(order)}
            for fut in as_completed(futures):
                c = futures[fut]
                try:
                    res = fut.result()
                except Exception as err:  # the worker died (KilledWorker, ...)
                    res = _lost(c, err)
                land(c, res)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    write_results_csv(out / "results.csv", all_rows())
    outcome.records = [records[i] for i in ids if i in records] + others
    outcome.wall_s = time.perf_counter() - t0
    return outcome


def _other_records(out: Path, ids: set[str]) -> list[dict[str, Any]]:
    """Finished cells under ``out`` from other grids (an extended sweep: more seeds, another
    preset), by id: results.csv and the tables hold every finished cell of the directory."""
    recs = []
    for p in sorted((out / "cells").glob("*/cell.json")):
        if p.parent.name in ids:
            continue
        try:
            rec = read_json(p)
        except Exception:  # a damaged record is not a result
            continue
        if isinstance(rec, dict) and rec.get("row", {}).get("status") == "ok":
            recs.append(rec)
    return recs


def _lost(c: Cell, err: BaseException) -> CellResult:
    row: dict[str, Any] = dict.fromkeys(COLUMN_NAMES, "")
    row.update(cell=c.id, forest=c.forest, mode=c.mode, seed=c.seed, sic=c.sic,
               preset=c.preset, status="failed",
               error=f"{type(err).__name__}: {err}".replace("\n", " ")[:500])
    return CellResult(row, {"traceback": repr(err)})
