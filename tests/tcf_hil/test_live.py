"""The live figures of a run (``tcf-hil run``, ``replay``, ``soak``): the line a terminal
shows, and the live score computed in a helper process, which must be the score the run
writes at the end for the same publication. (The displays themselves are tested in a
pseudo-terminal with the runs: test_bridge, test_soak, test_faults_in_runs,
test_experiments.)"""

from __future__ import annotations

import json
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tcf_hil.evaluation.scoring import score_forest
from tcf_hil.recording.stems_json import stem_table
from tcf_hil.run import LiveFigures
from tcf_hil.run._figures import LiveScore
from tcf_hil.world.forest import Forest, ground_truth


def test_the_line_names_every_figure_known() -> None:
    f = LiveFigures(phase="streaming", sim_s=31.24, sim_total_s=100.0, frames_sent=312,
                    frames_total=1000, behind_s=0.8, frames_lost=2, refused=1, can=3120,
                    publications=6, invalid=1, wc_all=54.25, f1_all=0.714, scored=5)
    assert f.line() == ("sim 31.2/100.0 s · frames 312/1000 (0.8 s behind), lost 2, "
                        "1 datagrams refused · CAN poses 3120 · publications 6 (1 invalid) · "
                        "wc all 54.2 % (F1 0.71, #5)")
    # a replay without a SIC: no publications, its own CAN noun, no score yet
    g = LiveFigures(sim_s=-0.4, frames_sent=3, can=7, can_noun="CAN frames")
    assert g.line() == "sim 0.0 s · frames 3 · CAN frames 7"


@settings(max_examples=60, deadline=None)
@given(st.builds(LiveFigures, sim_s=st.none() | st.floats(-5, 1e5),
                 sim_total_s=st.none() | st.floats(0.1, 1e5),
                 frames_sent=st.integers(0, 10**7), frames_lost=st.integers(0, 10**5),
                 behind_s=st.floats(0, 1e3), can=st.integers(0, 10**8),
                 publications=st.none() | st.integers(0, 10**4),
                 wc_all=st.none() | st.floats(0, 100), f1_all=st.none() | st.floats(0, 1),
                 scored=st.integers(1, 10**4)))
def test_the_line_is_one_line_and_never_fails(f: LiveFigures) -> None:
    line = f.line()
    assert "\n" not in line and f"frames {f.frames_sent}" in line
    assert ("publications" in line) == (f.publications is not None)
    assert ("wc all" in line) == (f.wc_all is not None)


def test_the_live_score_is_the_runs_score_of_that_publication(forest_ii: Forest,
                                                              tmp_path: Path) -> None:
    gt = ground_truth(forest_ii)
    # a SIC's forest: two thirds of the trees, a few centimetres off, one class wrong
    objs = [dict(o, cp=[o["cp"][0] + 0.03, o["cp"][1] - 0.02, o["cp"][2]])
            for o in gt["objects"][::3] + gt["objects"][1::3]]
    objs[0].update({"class": "X", "quality": 3} if objs[0]["class"] != "X"
                   else {"class": "S", "quality": 1})
    docs = []
    for n, sel in enumerate((objs[:5], objs), 1):
        path = tmp_path / f"{n:04d}.json"
        path.write_text(json.dumps({"objects": sel}))
        docs.append(path)
    live = LiveScore(gt)
    try:
        for n, path in enumerate(docs, 1):
            live.offer(n, path)
            deadline = time.monotonic() + 60
            while (live.result is None or live.result[0] != n) and time.monotonic() < deadline:
                time.sleep(0.05)
                live.collect()
            assert live.result is not None and live.result[0] == n
            want = score_forest(gt, stem_table(json.loads(path.read_text()), "x", "observed"))
            fig = LiveFigures()
            live.fill(fig)
            assert fig.scored == n
            assert fig.wc_all == pytest.approx(want.all.metrics["evaluation_score_percent"])
            assert fig.f1_all == pytest.approx(want.all.metrics["f1"])
        assert 0 < fig.f1_all < 1  # (the last: a forest partly found)
        live.offer(1, docs[0])  # an older publication than the one scored is not scored
        assert live._pending is None
    finally:
        live.close()
