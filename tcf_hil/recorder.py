"""The recorder's side of a run: the SIC's publications (stdout NDJSON, a file it rewrites,
HTTP POST), each kept as it arrived in ``sic/NNNN.json`` with a line in ``sic/index.ndjson``;
scoring of a forest against all ground-truth trees and the trees the sensor saw."""

from __future__ import annotations

import json
import math
import os
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import IO, Any

import numpy as np
from numpy.typing import NDArray

from tcf_hil._io import ensure_dir, loads_json, write_bytes_atomic
from tcf_hil.errors import InputError
from tcf_hil.evaluation import EvalConfig, Evaluation, evaluate
from tcf_hil.stems_json import StemTable, stem_table

MAX_PUBLICATION_BYTES = 32 << 20


@dataclass
class Publication:
    n: int
    file: str
    via: str
    arrival_s: float  # since the run started
    bytes: int
    valid: bool
    error: str | None
    objects: int | None
    table: StemTable | None = field(default=None, repr=False)

    def index_row(self) -> dict[str, Any]:
        return {"n": self.n, "file": self.file, "via": self.via,
                "arrival_s": round(self.arrival_s, 6), "bytes": self.bytes,
                "valid": self.valid, "error": self.error, "objects": self.objects}


class Inbox:
    """Receives publications from any channel, keeps each, validates it against the
    observed-forest schema; the latest valid one is what gets scored."""

    def __init__(self, sic_dir: Path, t0: float | None = None) -> None:
        self.dir = ensure_dir(sic_dir)
        self.t0 = t0 if t0 is not None else time.monotonic()
        self._lock = threading.Lock()
        self.items: list[Publication] = []
        self.non_json_lines = 0
        self._index: IO[str] = open(self.dir / "index.ndjson", "a", encoding="utf-8")

    def record(self, raw: bytes, via: str) -> Publication:
        with self._lock:
            n = len(self.items) + 1
            name = f"{n:04d}.json"
            write_bytes_atomic(self.dir / name, raw)
            arrival = time.monotonic() - self.t0
            table: StemTable | None = None
            err: str | None = None
            if len(raw) > MAX_PUBLICATION_BYTES:
                err = f"{len(raw)} bytes; at most {MAX_PUBLICATION_BYTES} accepted"
            else:
                try:
                    doc = loads_json(raw.decode("utf-8", errors="replace"), f"sic/{name}")
                    table = stem_table(doc, f"sic/{name}", "observed")
                except InputError as e:
                    err = str(e)
            pub = Publication(n, name, via, arrival, len(raw), table is not None, err,
                              len(table) if table is not None else None, table)
            if table is not None:  # only the latest valid table stays in memory (a long run
                for old in reversed(self.items):  # publishes hundreds): see table_of()
                    if old.table is not None:
                        old.table = None
                        break
            self.items.append(pub)
            self._index.write(json.dumps(pub.index_row()) + "\n")
            self._index.flush()
            return pub

    def table_of(self, pub: Publication) -> StemTable:
        """The stem table of a valid publication (read back from its file unless it is the
        latest)."""
        if pub.table is not None:
            return pub.table
        if not pub.valid:
            raise ValueError(f"publication {pub.n} is not valid: {pub.error}")
        name = f"sic/{pub.file}"
        return stem_table(loads_json((self.dir / pub.file).read_text(encoding="utf-8",
                                                                     errors="replace"), name),
                          name, "observed")

    @property
    def valid(self) -> list[Publication]:
        with self._lock:
            return [p for p in self.items if p.valid]

    @property
    def invalid(self) -> list[Publication]:
        with self._lock:
            return [p for p in self.items if not p.valid]

    def close(self) -> None:
        self._index.close()


class PublishServer:
    """``POST /publish`` on 127.0.0.1: the body is one forest document. Answers 200 when it is
    valid, 400 with the reason when not (kept either way), 413 when too large."""

    def __init__(self, inbox: Inbox, host: str = "127.0.0.1", port: int = 0) -> None:
        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"

            def log_message(self, format: str, *args: Any) -> None:
                pass

            def _answer(self, status: int, body: dict[str, Any]) -> None:
                data = json.dumps(body).encode()
                self.send_response(status)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)

            def do_POST(self) -> None:
                if self.path.split("?")[0].rstrip("/") != "/publish":
                    self._answer(404, {"error": f"no such path {self.path[:80]!r}; POST the "
                                                "forest to /publish"})
                    return
                try:
                    length = int(self.headers.get("Content-Length", ""))
                except ValueError:
                    self._answer(411, {"error": "Content-Length required"})
                    return
                if length > MAX_PUBLICATION_BYTES or length < 0:
                    self.close_connection = True
                    self._answer(413, {"error": f"at most {MAX_PUBLICATION_BYTES} bytes"})
                    return
                pub = inbox.record(self.rfile.read(length), "http")
                self._answer(200 if pub.valid else 400,
                             {"n": pub.n, "valid": pub.valid, "error": pub.error})

            def do_GET(self) -> None:
                self._answer(405, {"error": "POST the forest to /publish"})

        self.server = ThreadingHTTPServer((host, port), Handler)
        self.server.daemon_threads = True
        self.url = f"http://{host}:{self.server.server_address[1]}/publish"
        self._thread = threading.Thread(target=self.server.serve_forever,
                                        name="publish-http", daemon=True)

    def start(self) -> PublishServer:
        self._thread.start()
        return self

    def close(self) -> None:
        if self._thread.is_alive():  # shutdown() waits for a serve_forever that never ran
            self.server.shutdown()
        self.server.server_close()


class FileWatcher(threading.Thread):
    """Records ``path`` each time the SIC replaces it (polled)."""

    def __init__(self, inbox: Inbox, path: Path, period_s: float = 0.1) -> None:
        super().__init__(name="publish-file", daemon=True)
        self.inbox, self.path, self.period = inbox, path, period_s
        self.stop = threading.Event()
        self._seen: tuple[int, int, int] | None = None

    def poll(self) -> None:
        try:
            st = os.stat(self.path)
        except OSError:
            return
        key = (st.st_ino, st.st_mtime_ns, st.st_size)
        if key != self._seen:
            self._seen = key
            try:
                with open(self.path, "rb") as fh:  # bounded: a huge file is not read whole
                    data = fh.read(MAX_PUBLICATION_BYTES + 1)
            except OSError:
                return
            self.inbox.record(data, "file")

    def run(self) -> None:
        while not self.stop.wait(self.period):
            self.poll()
        self.poll()

    def close(self) -> None:
        self.stop.set()
        self.join(timeout=2.0)


# ------------------------------------------------------------------------------- scoring
def seen_truth(gt_doc: dict[str, Any]) -> dict[str, Any]:
    """The ground truth restricted to the stems with at least one lidar return; a field
    inventory, which knows nothing of what the sensor saw, as it is."""
    if "inventory" in gt_doc:
        return gt_doc
    objs = [o for o in gt_doc["objects"] if int(o.get("returns", 0)) > 0]
    return {**gt_doc, "objects": objs, "total_objects_count": len(objs)}


@dataclass
class Scores:
    all: Evaluation
    seen: Evaluation
    gt_all: StemTable
    gt_seen: StemTable

    def summary(self) -> dict[str, Any]:
        return {"all_trees": self.all.metrics, "seen_trees": self.seen.metrics}


DISTANCE_BANDS_M = ((0.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 25.0), (25.0, math.inf))


def by_distance(ev: Evaluation, gt: StemTable, obs: StemTable, gt_d: NDArray[np.float64],
                obs_d: NDArray[np.float64],
                bands: tuple[tuple[float, float], ...] = DISTANCE_BANDS_M
                ) -> list[dict[str, Any]]:
    """The scoring per band of horizontal distance from the track (the report's "Errors by
    distance", for scripts): a true stem counts in the band of its own distance, a SIC stem
    in its own (an unmatched one is a false positive there). Per band: trees, found,
    detection, SIC stems, false positives and their share, position RMSE, DBH bias and
    RMSE, class correct (of the found)."""
    g2o = {int(g): int(o) for g, o in ev.pairs}
    matched = set(g2o.values())
    out = []
    for lo, hi in bands:
        gi = np.flatnonzero((gt_d >= lo) & (gt_d < hi))
        oi = np.flatnonzero((obs_d >= lo) & (obs_d < hi))
        m = [(g, g2o[g]) for g in gi.tolist() if g in g2o]
        fp = sum(1 for o in oi.tolist() if o not in matched)
        pos = [math.dist(gt.xyz[g, :2], obs.xyz[o, :2]) for g, o in m]
        dbh = [float(obs.dbh[o] - gt.dbh[g]) for g, o in m
               if math.isfinite(obs.dbh[o]) and math.isfinite(gt.dbh[g])]
        cls = [obs.classes[o] == gt.classes[g] for g, o in m]

        def rms(v: list[float]) -> float | None:
            return round(math.sqrt(sum(e * e for e in v) / len(v)), 4) if v else None

        out.append({
            "from_m": lo, "to_m": None if math.isinf(hi) else hi, "trees": len(gi),
            "found": len(m), "detection": round(len(m) / len(gi), 4) if len(gi) else None,
            "sic_stems": len(oi), "false_positives": fp,
            "false_positive_share": round(fp / len(oi), 4) if len(oi) else None,
            "position_rmse_m": rms(pos),
            "dbh_bias_m": round(sum(dbh) / len(dbh), 4) if dbh else None,
            "dbh_rmse_m": rms(dbh),
            "class_correct": round(sum(cls) / len(cls), 4) if cls else None})
    return out


def score_forest(gt_doc: dict[str, Any], obs: StemTable, cfg: EvalConfig | None = None,
                 gt_source: str = "ground_truth.json") -> Scores:
    """``obs`` scored against a generated forest's ground truth or a field inventory
    (:func:`tcf_hil.inventory.read_inventory`: the metrics it cannot give are None)."""
    if "inventory" in gt_doc:  # all trees count as seen: one evaluation serves both
        gt = stem_table(gt_doc, gt_source, "observed")
        ev = evaluate(gt, obs, cfg)
        blank_absent(ev.metrics, gt_doc)
        return Scores(ev, ev, gt, gt)
    gt_all = stem_table(gt_doc, gt_source, "ground_truth")
    gt_seen = stem_table(seen_truth(gt_doc), gt_source, "ground_truth")
    scores = Scores(evaluate(gt_all, obs, cfg), evaluate(gt_seen, obs, cfg), gt_all, gt_seen)
    return scores


def blank_absent(metrics: dict[str, Any], gt_doc: dict[str, Any]) -> None:
    """Metrics whose inputs a field inventory lacks become None (absent, not zero): its
    missing columns', and the errors no matched pair had both values for."""
    from tcf_hil.inventory import absent_metrics

    for key in absent_metrics(gt_doc):
        metrics[key] = None
    if metrics.get("evaluation_score_percent", 0) is None:  # no classes: no EM either
        metrics["em"] = None
    if "inventory" in gt_doc:
        for name in ("height", "dbh", "maxcurve"):
            if not metrics[f"{name}_pairs"]:
                metrics[f"{name}_rmse_m"] = metrics[f"{name}_bias_m"] = None


def empty_forest() -> StemTable:
    return stem_table({"objects": []}, "<no publication>", "observed")
