"""The recorder's side of a run: the SIC's publications (stdout NDJSON, a file it rewrites,
HTTP POST), each kept as it arrived in ``sic/NNNN.json`` with a line in ``sic/index.ndjson``.
The scoring of a forest is :mod:`tcf_hil.evaluation.scoring`."""

from __future__ import annotations

import json
import os
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import IO, Any

from tcf_hil._io import ensure_dir, loads_json, write_bytes_atomic
from tcf_hil.errors import InputError
from tcf_hil.recording.stems_json import StemTable, stem_table

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
    doc: dict[str, Any] | None = field(default=None, repr=False)  # the latest's, with its table
    unix_ns: int | None = None  # when it arrived, on the clock the capture's times keep

    def index_row(self) -> dict[str, Any]:
        return {"n": self.n, "file": self.file, "via": self.via,
                "arrival_s": round(self.arrival_s, 6), "bytes": self.bytes,
                "valid": self.valid, "error": self.error, "objects": self.objects,
                "unix_ns": self.unix_ns}


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
            unix_ns = time.time_ns()
            table: StemTable | None = None
            doc: dict[str, Any] | None = None
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
                              len(table) if table is not None else None, table,
                              doc if table is not None else None, unix_ns)
            if table is not None:  # only the latest valid table stays in memory (a long run
                for old in reversed(self.items):  # publishes hundreds): see table_of()
                    if old.table is not None:
                        old.table = old.doc = None
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

    def doc_of(self, pub: Publication) -> dict[str, Any]:
        """The document of a valid publication (read back from its file unless it is the
        latest)."""
        if pub.doc is not None:
            return pub.doc
        if not pub.valid:
            raise ValueError(f"publication {pub.n} is not valid: {pub.error}")
        return loads_json((self.dir / pub.file).read_text(encoding="utf-8", errors="replace"),
                          f"sic/{pub.file}")

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
