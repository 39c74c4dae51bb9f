"""Faults of a live run: ``--fault KEY=VALUE`` applied to the scenario's ``[faults]`` section,
and the log the recorder keeps of every fault injected. The plans themselves are built once
per run, in its world (:mod:`tcf_hil.world.faults`).

Times in the scenario are seconds after the track starts; the plans work in simulation ns.
The draws are seeded from ``faults.seed`` (0: the run's seed), so a faulty run repeats
exactly.
"""

from __future__ import annotations

import collections
import json
import threading
import tomllib
from collections.abc import Iterable
from pathlib import Path
from typing import IO, Any

from emulators.faults import FaultEvent
from tcf_hil.errors import ConfigError
from tcf_hil.scenario import Scenario

__all__ = ["FaultLog", "apply_fault_options", "read_fault_log"]


def apply_fault_options(scn: Scenario, options: Iterable[str]) -> Scenario:
    """``scn`` with ``--fault KEY=VALUE`` options applied (KEY below ``faults.``, VALUE a TOML
    value: ``udp.loss=0.01``, ``can.bus_off_at_s=[20, 40]``, ``lidar.reinit_at_s=[30]``).
    Raises ConfigError naming the key."""
    from tcf_hil.scenario import scenario_from_dict, scenario_to_dict

    options = list(options)
    if not options:
        return scn
    data = scenario_to_dict(scn)
    for opt in options:
        key, sep, text = opt.partition("=")
        key = key.strip().removeprefix("faults.")
        if not sep or not key:
            raise ConfigError("--fault", opt, "KEY=VALUE, e.g. udp.loss=0.01", None)
        try:
            value = tomllib.loads(f"v = {text.strip()}")["v"]
        except tomllib.TOMLDecodeError:
            value = text.strip()  # a bare word: a string (udp.ports=lidar)
        node = data.setdefault("faults", {})
        *parents, leaf = key.split(".")
        for p in parents:
            nxt = node.get(p)
            if not isinstance(nxt, dict):
                raise ConfigError(f"faults.{key}", value,
                                  f"a key below one of: {', '.join(sorted(node))}", "--fault")
            node = nxt
        node[leaf] = value
    return scenario_from_dict(data, "--fault")


class FaultLog:
    """``faults.jsonl`` of a run: one line per injected fault event, with its simulation time
    (``t_s``, seconds after the track start) and its source. Thread-safe; counts by kind."""

    def __init__(self, path: Path | None, track_t0_ns: int) -> None:
        self.path = path
        self.t0_ns = track_t0_ns
        self._lock = threading.Lock()
        self._fh: IO[str] | None = open(path, "w", encoding="utf-8") if path else None
        self.counts: collections.Counter[str] = collections.Counter()
        self.events = 0
        self.first_s: dict[str, float] = {}
        self.last_s: dict[str, float] = {}

    def log(self, event: FaultEvent, source: str | None = None) -> None:
        """Write one event; ``source`` defaults to the kind's prefix (udp, lidar, can)."""
        kind = str(event.get("kind", "unknown"))
        source = source or kind.split("_", 1)[0]
        t_s = round((int(event.get("t_ns", self.t0_ns)) - self.t0_ns) / 1e9, 6)
        line = {"t_s": t_s, "source": source, **{k: v for k, v in event.items()
                                                 if k != "t_ns"}}
        with self._lock:
            self.events += 1
            self.counts[kind] += int(event.get("count", 1))
            self.first_s.setdefault(kind, t_s)
            self.last_s[kind] = t_s
            if self._fh is not None:
                self._fh.write(json.dumps(line, separators=(",", ":")) + "\n")

    def summary(self) -> dict[str, Any]:
        """Per kind: how many (datagrams, frames or events) and the first and last time."""
        with self._lock:
            return {k: {"count": n, "first_s": self.first_s[k], "last_s": self.last_s[k]}
                    for k, n in sorted(self.counts.items())}

    def close(self) -> None:
        with self._lock:
            if self._fh is not None:
                self._fh.close()
                self._fh = None


def read_fault_log(path: Path) -> list[dict[str, Any]]:
    """The events of a run's ``faults.jsonl`` (empty when the file is missing)."""
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines()
            if line.strip()]
