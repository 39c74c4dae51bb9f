"""What a run has done so far, for the person watching it (``tcf-hil run``, ``replay``,
``soak``): the simulation time, frames sent and lost, CAN traffic, the SIC's publications
and the score of its latest forest.

The live score is computed in a helper process of its own: scoring a Forest V forest takes
~80 ms of Python, and in the bench's process it would hold the interpreter lock the UDP
sender's pacing loop needs (the sender shares this process; see
:func:`tcf_hil.devices.lidar.stream_lidar`). The helper scores only the latest valid publication,
and only when the previous score is done: a SIC that publishes faster than it is scored is
shown its newest forest, never a queue of old ones.
"""

from __future__ import annotations

import concurrent.futures as cf
import contextlib
import multiprocessing as mp
import os
import signal
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class LiveFigures:
    """A run's figures so far. ``None``: not known (yet) for this traffic."""

    phase: str = "starting"
    #: simulation seconds since the track's start (a replay: seconds into the recording)
    sim_s: float | None = None
    sim_total_s: float | None = None
    frames_sent: int = 0
    frames_total: int | None = None
    #: how far the frames sent lag the clock (simulation seconds; the machine cannot keep
    #: this speed when it grows)
    behind_s: float = 0.0
    #: frames that did not leave whole: an injected fault dropped the frame or some of its
    #: datagrams (udp.loss, udp.burst_rate, lidar.dropout)
    frames_lost: int = 0
    #: datagrams the kernel refused to send (the socket's buffer was full)
    refused: int = 0
    #: pose samples the harvester node published on CAN (a replay: CAN frames sent)
    can: int = 0
    can_noun: str = "CAN poses"
    #: the SIC's publications (None: no SIC in this run, the traffic alone)
    publications: int | None = None
    invalid: int = 0
    #: the score of publication ``scored`` against all trees (None: none scored yet)
    wc_all: float | None = None
    f1_all: float | None = None
    scored: int | None = None
    #: the latest valid publication's number (None: none yet)
    latest_publication: int | None = None
    #: the run directory (None: a run that records nothing) and the run's world (a live
    #: run's :class:`~tcf_hil.world.World`; None for recorded traffic): for live views
    run_dir: Path | None = field(default=None, repr=False)
    world: Any = field(default=None, repr=False)

    def line(self) -> str:
        """One line for a terminal, e.g. ``sim 31.2/100.0 s · frames 312/1000, lost 2 ·
        CAN poses 3120 · publications 6 · wc all 54.2 % (F1 0.71, #6)``."""
        parts = []
        if self.sim_s is not None:
            total = f"/{self.sim_total_s:.1f}" if self.sim_total_s else ""
            parts.append(f"sim {max(self.sim_s, 0.0):.1f}{total} s")
        frames = f"frames {self.frames_sent}" + (
            f"/{self.frames_total}" if self.frames_total else "")
        if self.behind_s >= 0.5:
            frames += f" ({self.behind_s:.1f} s behind)"
        if self.frames_lost:
            frames += f", lost {self.frames_lost}"
        if self.refused:
            frames += f", {self.refused} datagrams refused"
        parts.append(frames)
        parts.append(f"{self.can_noun} {self.can}")
        if self.publications is not None:
            pubs = f"publications {self.publications}"
            if self.invalid:
                pubs += f" ({self.invalid} invalid)"
            parts.append(pubs)
        if self.wc_all is not None:
            f1 = f"F1 {self.f1_all:.2f}, " if self.f1_all is not None else ""
            parts.append(f"wc all {self.wc_all:.1f} % ({f1}#{self.scored})")
        return " · ".join(parts)


# ------------------------------------------------------------------------- the live score
_TRUTH: Any = None


def _init(gt_doc: dict[str, Any], cfg: Any) -> None:
    global _TRUTH
    # a terminal's Ctrl-C reaches the whole process group: the session decides when this
    # helper stops; and the pacing loop, not the score, gets the CPU when both want it
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    with contextlib.suppress(OSError):
        os.nice(19)
    import tcf_hil.evaluation
    import tcf_hil.run.recorder  # noqa: F401 - imported once, as the process starts
    from tcf_hil.recording.stems_json import stem_table

    if "inventory" in gt_doc:  # (a field inventory is read as observed stems)
        _TRUTH = (gt_doc, stem_table(gt_doc, "ground truth", "observed"), cfg)
    else:
        _TRUTH = (gt_doc, stem_table(gt_doc, "ground truth", "ground_truth"), cfg)


def _score(path: str) -> tuple[float | None, float | None]:
    from tcf_hil._io import loads_json
    from tcf_hil.evaluation import evaluate
    from tcf_hil.evaluation.scoring import blank_absent
    from tcf_hil.recording.stems_json import stem_table

    gt_doc, gt, cfg = _TRUTH
    obs = stem_table(loads_json(Path(path).read_text(encoding="utf-8", errors="replace"),
                                path), path, "observed")
    ev = evaluate(gt, obs, cfg)  # (score_forest's "all trees" evaluation, without "seen")
    if "inventory" in gt_doc:
        blank_absent(ev.metrics, gt_doc)
    wc, f1 = ev.metrics.get("evaluation_score_percent"), ev.metrics.get("f1")
    return (None if wc is None else float(wc)), (None if f1 is None else float(f1))


class LiveScore:
    """Scores the latest valid publication against ``gt_doc`` (all trees, with the run's
    ``cfg``) in a helper process (see the module docstring). :meth:`offer` is called often
    and never waits."""

    def __init__(self, gt_doc: dict[str, Any], cfg: Any = None) -> None:
        # spawned, not forked: the bench has threads and a frame producer by now
        self._pool = cf.ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"),
                                            initializer=_init, initargs=(gt_doc, cfg))
        self._pool.submit(int)  # the helper starts (and imports) now, while the SIC does
        self._pending: tuple[int, cf.Future[tuple[float | None, float | None]]] | None = None
        self._asked = 0
        self.result: tuple[int, float | None, float | None] | None = None

    def offer(self, n: int, path: Path) -> None:
        """Publication ``n`` (its file ``path``) is the latest valid one."""
        self.collect()
        if self._pending is None and n > self._asked:
            self._asked = n
            self._pending = (n, self._pool.submit(_score, str(path)))

    def collect(self) -> None:
        if self._pending is not None and self._pending[1].done():
            n, fut = self._pending
            self._pending = None
            try:
                wc, f1 = fut.result()
            except Exception:  # the run's own score at the end says why
                return
            self.result = (n, wc, f1)

    def fill(self, fig: LiveFigures) -> None:
        self.collect()
        if self.result is not None:
            fig.scored, fig.wc_all, fig.f1_all = self.result

    def close(self) -> None:
        """Stop at once: a score under way is not waited for (nobody will see it)."""
        procs = list((getattr(self._pool, "_processes", None) or {}).values())
        self._pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            with contextlib.suppress(Exception):
                p.terminate()
                p.join(2.0)
