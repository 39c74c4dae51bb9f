"""Experiments at scale: cells through the wire's bytes, sweeps on a 2-worker Dask
LocalCluster (rerun skips, a failing SIC fails only its cell), the results.csv contract, the
summary statistics, multi-pass scanning and the speed-against-error bench."""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from _tty import run_in_terminal
from hypothesis import given, settings
from hypothesis import strategies as st

from emulators.jit import jit_enabled
from tcf_hil.experiments.bench import pareto
from tcf_hil.experiments.cells import COLUMN_NAMES, SAMPLED, make_cell, run_cell
from tcf_hil.experiments.offline import run_offline
from tcf_hil.experiments.sweep import _worker_env, estimated_cost, run_sweep
from tcf_hil.experiments.tables import ci95, write_tables
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict, with_sensor

TCF = [sys.executable, "-m", "tcf_hil"]
ENV = dict(os.environ, COLUMNS="200")
FAIL_SIC = "{python} -c \"import sys; print('giving up', file=sys.stderr); sys.exit(4)\""


def _read_csv(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    with path.open(newline="") as fh:
        r = csv.DictReader(fh)
        return list(r.fieldnames or []), list(r)


def _events(progress: list[tuple[str, dict]] | None = None
            ) -> tuple[list[tuple[str, str]], object]:
    """(kind, cell id) of every event but 'progress' (whose rows go to ``progress``)."""
    seen: list[tuple[str, str]] = []

    def on_event(kind: str, cell: object, row: dict | None) -> None:
        if kind != "progress":
            seen.append((kind, cell.id))  # type: ignore[attr-defined]
        elif progress is not None and row is not None:
            progress.append((cell.id, row))  # type: ignore[attr-defined]
    return seen, on_event


@pytest.mark.slow  # the second lane (.ci/run): a Dask cluster's start-up (the local
# executor's sweeps stay in the first lane)
def test_sweep_on_a_two_worker_local_cluster_then_a_rerun_skips(tmp_path: Path) -> None:
    # 2.5 s of track: most stems glimpsed once from 10-25 m, a row of returns every 1.4 deg.
    # The tuned preset's radius graph joins such rows into stems; the field preset (the
    # default, built for a pass) finds only those within about 10 m (README, "The
    # field-grade reference SIC", what it does not yet do), so the sweep's own checks run
    # on tuned here
    cells = [make_cell(with_sensor(load_scenario(f), "ideal"), m, max_frames=25,
                       preset="tuned")
             for f in ("forest-i", "forest-ii") for m in ("512x10", "1024x10")]
    progress: list[tuple[str, dict]] = []
    seen, on_event = _events(progress)
    out = run_sweep(cells, tmp_path, executor="local", workers=2, on_event=on_event)
    assert (out.ran, out.skipped, out.failed) == (4, 0, [])
    # the workers' frames reached this process while the cells ran (the scheduler's events)
    for c in cells:
        frames = [row["frames"] for cid, row in progress if cid == c.id]
        assert frames and frames == sorted(frames) and 1 <= frames[0] <= frames[-1] <= 25, c
        assert all(row["total"] == 25 for cid, row in progress if cid == c.id)
    # the two costliest cells started first, one on each worker
    started = list(dict.fromkeys(cid for cid, _ in progress))
    assert set(started[:2]) == {c.id for c in sorted(cells, key=estimated_cost)[2:]}
    head, rows = _read_csv(tmp_path / "results.csv")
    assert head == list(COLUMN_NAMES)
    assert [r["cell"] for r in rows] == [c.id for c in cells]  # grid order, not finish order
    for r in rows:
        assert r["status"] == "ok", r["error"]
        assert 0.0 <= float(r["all_wc"]) <= 100.0
        assert int(r["frames"]) == 25 and int(r["stems_seen"]) <= int(r["stems"])
        assert float(r["all_wc"]) > 50.0  # the reference SIC finds these small forests
        assert r["worker"].split(":")[-1] != str(os.getpid())  # ran in a worker process
    assert sorted(k for k, _ in seen) == ["done"] * 4
    # the same cell in this process gives the same row: cells are deterministic
    again = run_cell(cells[1])
    first = next(r for r in rows if r["cell"] == cells[1].id)
    assert f"{again.row['all_wc']:.6g}" == first["all_wc"]
    assert f"{again.row['all_position_rmse_m']:.6g}" == first["all_position_rmse_m"]

    before = (tmp_path / "results.csv").read_bytes()
    seen2, on_event2 = _events()
    out2 = run_sweep(cells, tmp_path, executor="local", workers=2, on_event=on_event2)
    assert (out2.ran, out2.skipped) == (0, 4)
    assert [k for k, _ in seen2] == ["skipped"] * 4
    assert (tmp_path / "results.csv").read_bytes() == before
    # a smaller grid into the same directory keeps every finished cell in the table
    out3 = run_sweep(cells[2:3], tmp_path, executor="inline")
    assert (out3.ran, out3.skipped, len(out3.records)) == (0, 1, 4)
    _, rows3 = _read_csv(tmp_path / "results.csv")
    assert rows3[0]["cell"] == cells[2].id
    assert sorted(r["cell"] for r in rows3) == sorted(c.id for c in cells)
    # a changed spec under the same id is not "finished"
    changed = [dataclasses.replace(cells[0], max_frames=20)]
    assert run_sweep(changed, tmp_path / "x", executor="inline").ran == 1


def test_local_workers_share_the_cpus_and_the_costliest_cells_go_first(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("TCF_HIL_RAY_THREADS", raising=False)
    cpus = len(os.sched_getaffinity(0))
    assert _worker_env(2) == {"TCF_HIL_RAY_THREADS": str(max(1, cpus // 2))}
    assert _worker_env(10 * cpus) == {"TCF_HIL_RAY_THREADS": "1"}
    monkeypatch.setenv("TCF_HIL_RAY_THREADS", "3")  # the user's word stands
    assert _worker_env(2) == {}

    def cost(forest: str, mode: str) -> float:
        return estimated_cost(make_cell(load_scenario(forest), mode))

    assert cost("forest-v-natural", "1024x10") > cost("forest-v", "1024x10")
    assert cost("forest-v", "2048x10") > cost("forest-v", "1024x10") > cost("forest-v", "512x10")
    assert cost("forest-x", "512x10") > cost("forest-i", "512x10")
    assert cost("forest-v", SAMPLED) < cost("forest-v", "512x10")


@pytest.mark.slow  # the second lane (.ci/run): out of the fast lane's ten minutes
def test_a_failing_sic_fails_its_cell_only_and_a_rerun_retries_it(tmp_path: Path) -> None:
    """On a running scheduler by its address (dask://HOST:PORT), as on a real cluster."""
    from dask.distributed import LocalCluster

    scn = load_scenario("forest-ii")
    good = make_cell(scn, "512x10", max_frames=20)
    bad = make_cell(scn, "512x10", sic=FAIL_SIC, max_frames=20)
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        address = cluster.scheduler_address.replace("tcp://", "dask://")
        out = run_sweep([good, bad], tmp_path, executor=address)
    assert out.ran == 2 and len(out.failed) == 1
    f = out.failed[0]
    assert f["cell"] == bad.id and f["status"] == "failed"
    assert "exited" in f["error"] and "SIC" in f["error"]
    assert (tmp_path / "cells" / bad.id / "failed.json").exists()
    assert (tmp_path / "cells" / bad.id / "run" / "sic" / "stderr.log").read_text().strip() \
        == "giving up"
    _, rows = _read_csv(tmp_path / "results.csv")
    assert [r["status"] for r in rows] == ["ok", "failed"]
    paths = write_tables(out.records, tmp_path, out.failed)
    md = paths["summary.md"].read_text()
    assert "## Failed cells" in md and bad.id in md
    out2 = run_sweep([good, bad], tmp_path, executor="inline")
    assert (out2.ran, out2.skipped, len(out2.failed)) == (1, 1, 1)


def test_unknown_executor_is_refused() -> None:
    cell = make_cell(load_scenario("forest-i"), "512x10")
    with pytest.raises(ValueError, match="dask://HOST:PORT"):
        run_sweep([cell], "/nonexistent-never-created", executor="spark://x")


def test_poses_reach_the_sic_through_the_can_frames() -> None:
    """A GNSS bias on the bus (truth unchanged) moves every stem the SIC finds by it."""
    base = with_sensor(load_scenario("forest-ii"), "ideal")  # the poses alone move stems
    d = scenario_to_dict(base)
    d["harvester"]["pose_error"]["bias_m"] = [0.4, 0.0, 0.0]
    biased = scenario_from_dict(d)
    r0 = run_offline(base, mode="512x10", max_frames=60)
    r1 = run_offline(biased, mode="512x10", max_frames=60)
    b0 = r0.scores.all.metrics["position_bias_m"]
    b1 = r1.scores.all.metrics["position_bias_m"]
    assert abs(b0[0]) < 0.05 and abs(b0[1]) < 0.05
    assert b1[0] == pytest.approx(0.4, abs=0.05) and abs(b1[1]) < 0.05
    assert r0.poses >= 60 * 10  # 100 Hz over 6 s of frames
    assert r0.frames == 60 and r0.packets == 60 * 512 // 16


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_multi_pass_sees_more_of_the_same_forest(tmp_path: Path) -> None:
    """A 90 m wide stand with two strip roads 44 m apart: from one road the far edge lies
    beyond the 50 m range; the second pass, on the other road, brings it in."""
    toml = tmp_path / "strip.toml"
    toml.write_text('extends = "forest-iii"\nname = "strip-wide"\n[plot]\nsize_m = [90.0, 30.0]\n'
                    '[stems]\ncount = 200\n[distribution]\nstrip_roads = 2\n[track]\n'
                    'start_m = [22.0, -20.0, 2.0]\nend_m = [22.0, 20.0, 2.0]\nspeed_m_s = 4.0\n'
                    'pass_offset_m = 44.0\n[sensor]\npreset = "ideal"\n')  # a 50 m reach
    scn = load_scenario(str(toml))
    rows, truth = {}, {}
    for n in (1, 2):
        s = dataclasses.replace(scn, track=dataclasses.replace(scn.track, passes=n))
        res = run_cell(make_cell(s, "512x10", tag=f"p{n}"))
        assert res.row["status"] == "ok", res.row["error"]
        rows[n] = res.row
        truth[n] = res.row["stems"]
    assert truth[1] == truth[2] == 200
    assert rows[2]["sim_s"] > 2 * rows[1]["sim_s"]
    assert rows[1]["stems_seen"] < 190 and rows[2]["stems_seen"] == 200
    assert rows[2]["all_total_matches"] > rows[1]["all_total_matches"] + 20


def test_sampled_cell_is_the_papers_experiment_without_lidar() -> None:
    res = run_cell(make_cell(load_scenario("forest-i"), SAMPLED))
    assert res.row["status"] == "ok", res.row["error"]
    assert res.row["stems_seen"] == res.row["stems"] == 10
    assert res.row["frames"] == 0 and res.row["all_total_matches"] == 10


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=1, max_size=12))
def test_ci95_matches_scipys_t_interval(values: list[float]) -> None:
    from scipy import stats

    mean, half = ci95(values)
    assert mean == pytest.approx(float(np.mean(values)), abs=1e-9)
    if len(values) < 2:
        assert math.isnan(half)
        return
    assert half >= 0.0
    sd = float(np.std(values, ddof=1))
    if sd == 0.0:
        assert half == 0.0
        return
    lo, hi = stats.t.interval(0.95, len(values) - 1, loc=mean, scale=sd / math.sqrt(len(values)))
    assert half == pytest.approx((hi - lo) / 2, rel=1e-9, abs=1e-9)


@given(st.lists(st.tuples(st.floats(0, 100), st.floats(0, 100)), min_size=1, max_size=30))
def test_pareto_front_is_exactly_the_undominated_points(pts: list[tuple[float, float]]) -> None:
    cost = [p[0] for p in pts]
    err = [p[1] for p in pts]
    front = pareto(cost, err)
    for i in range(len(pts)):
        dominated = any((cost[j] <= cost[i] and err[j] < err[i])
                        or (cost[j] < cost[i] and err[j] <= err[i]) for j in range(len(pts)))
        if i in front:
            assert not dominated
        elif not dominated:  # an equal twin of a front point
            assert any(cost[j] == cost[i] and err[j] == err[i] for j in front)
    assert [cost[i] for i in front] == sorted(cost[i] for i in front)


def test_every_results_column_is_documented_in_the_readme() -> None:
    readme = (Path(__file__).parents[2] / "README.md").read_text()
    section = readme.split("### results.csv", 1)[1].split("\n## ", 1)[0]
    documented = re.findall(r"^\| `([a-z0-9_]+)` \|", section, flags=re.M)
    assert documented == list(COLUMN_NAMES)


@pytest.mark.slow  # the second lane (.ci/run): out of the fast lane's ten minutes
def test_cli_paper_writes_tables_figures_and_refuses_bad_forests(tmp_path: Path) -> None:
    """In a terminal: the running cell's frames and simulation time, then its score."""
    rc, screen = run_in_terminal([*TCF, "experiment", "paper", "--forests", "I", "--modes",
                                  "512x10,sampled", "--frames", "20", "--executor", "inline",
                                  "--out", str(tmp_path)], env=ENV, timeout=600)
    assert rc == 0, "\n".join(screen[-40:])
    assert any(re.search(r"forest-i-512x10\S* frames \d+/20, sim \d\.\d s", x) for x in screen)
    assert any("latest: forest-i-" in x and "wc " in x for x in screen)
    md = (tmp_path / "summary.md").read_text()
    assert "Table 9 layout" in md and "Table 10 layout" in md and "W 2-1-1" in md
    assert "70.0" in md  # the paper's Experiment 5 example beside ours
    assert (tmp_path / "heatmaps" / "forest-i-field.png").read_bytes()[:4] == b"\x89PNG"
    assert (tmp_path / "weighting.png").exists()
    _, rows = _read_csv(tmp_path / "results.csv")
    assert {r["mode"] for r in rows} == {"512x10", SAMPLED}
    bad = subprocess.run([*TCF, "experiment", "paper", "--forests", "XI", "--out",
                          str(tmp_path / "b")], capture_output=True, text=True, env=ENV)
    assert bad.returncode == 2 and "--forests" in bad.stderr and "'XI'" in bad.stderr
    assert not (tmp_path / "b").exists()


@pytest.mark.slow  # the second lane (.ci/run): an end-to-end run
def test_bench_quick(tmp_path: Path) -> None:
    p = subprocess.run([*TCF, "bench", "--quick", "--out", str(tmp_path)], capture_output=True,
                       text=True, env=ENV, timeout=600)
    assert p.returncode == 0, p.stderr
    _, rows = _read_csv(tmp_path / "bench.csv")
    mesh = [r for r in rows if r["stems_geometry"] == "mesh"]
    curves = [r for r in rows if r["stems_geometry"] == "curves"]
    backends = {r["backend"] for r in mesh}
    assert len(mesh) == 4 * len(backends) and "embree" in backends
    # and a row per preset with the stems as Embree's round curves (compiled kernels on)
    assert len(curves) == (2 if jit_enabled() else 0)
    assert all(r["backend"] == "embree" for r in curves)
    err = {float(r["tolerance_mm"]): float(r["range_err_p99_mm"]) for r in mesh}
    assert err[10.0] > err[2.0] > 0.0  # a coarser mesh costs range error
    assert all(float(r["range_err_p99_mm"]) < err[2.0] / 5 for r in curves)
    assert all(float(r["emulator_x_realtime"]) > 0 and float(r["sic_ms_p50"]) > 0 for r in rows)
    assert (tmp_path / "pareto.png").read_bytes()[:4] == b"\x89PNG"


@pytest.mark.slow  # the second lane (.ci/run): out of the fast lane's ten minutes
def test_bench_footprint_axis(tmp_path: Path) -> None:
    """off / adaptive / full x samples per FWHM: supersampled pixels, the returns' error against the
    exact surfaces and the DBH bias, beside an ideal sensor's."""
    args = [*TCF, "bench", "--quick", "--backends", "auto", "--presets", "tuned",
            "--tolerances", "2", "--frames", "20"]
    p = subprocess.run([*args, "--footprints", "off,adaptive:4,full:1", "--out",
                        str(tmp_path / "a")], capture_output=True, text=True, env=ENV,
                       timeout=600)
    assert p.returncode == 0, p.stderr
    _, rows = _read_csv(tmp_path / "a" / "bench.csv")
    by = {(r["footprint"], r["footprint_samples"]): r for r in rows}
    assert set(by) == {("off", "2"), ("adaptive", "4"), ("full", "1")}
    assert float(by["off", "2"]["supersampled_pct"]) == 0.0
    assert 0.0 < float(by["adaptive", "4"]["supersampled_pct"]) < 50.0
    assert float(by["full", "1"]["supersampled_pct"]) == 100.0
    assert all(r["sensor"] == "os0-64-rev7" and float(r["return_err_p50_mm"]) > 2.0
               for r in rows)  # the noise
    q = subprocess.run([*args, "--sensor", "ideal", "--out", str(tmp_path / "b")],
                       capture_output=True, text=True, env=ENV, timeout=600)
    assert q.returncode == 0, q.stderr
    _, (ideal,) = _read_csv(tmp_path / "b" / "bench.csv")
    assert ideal["sensor"] == "ideal" and float(ideal["return_err_p50_mm"]) < 2.0
    bad = subprocess.run([*args, "--footprints", "wide:3", "--out", str(tmp_path / "c")],
                         capture_output=True, text=True, env=ENV)
    assert bad.returncode == 2 and "--footprints" in bad.stderr
    assert not (tmp_path / "c").exists()


def test_strip_road_forest_does_not_depend_on_the_pass_count() -> None:
    from tcf_hil.experiments.cells import with_passes
    from tcf_hil.world.forest import generate_forest
    from tcf_hil.world.forest.placement import region_for

    scn = load_scenario("strip-road")
    bases = [generate_forest(with_passes(scn, n, None, 3)).stems.base for n in (1, 2, 3)]
    assert all(np.array_equal(bases[0], b) for b in bases[1:])
    cuts = region_for(scn).cuts
    assert [round((a + b) / 2, 6) for a, b in cuts] == [-20.0, 0.0, 20.0]
    xy = bases[0][:, :2]
    for road in (-20.0, 0.0, 20.0):  # no stem on any road
        assert np.min(np.abs(xy[:, 0] - road)) >= scn.distribution.corridor_half_width_m
