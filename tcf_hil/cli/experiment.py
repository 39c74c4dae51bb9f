"""``tcf-hil experiment`` and ``tcf-hil bench``: the paper's experiments, sweeps over
forests, modes and seeds (Dask), and speed against error."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import click
from rich.table import Table

from tcf_hil.cli._shared import (
    BACKEND_CHOICES,
    MODES,
    SIC_PRESETS,
    Group,
    Progress,
    announce_backend,
    console,
    err_console,
    mode_option,
    preset_option,
    sensor_option,
)
from tcf_hil.scenario import PRESET_NAMES, load_scenario, preset_name, with_sensor


@click.group(cls=Group)
def experiment() -> None:
    """The paper's experiments."""


def _experiment1(out: Path, seed: int | None, presets: Sequence[str], write_pcd: bool) -> None:
    from tcf_hil.experiments import run_experiment1

    announce_backend()
    with Progress("experiment 1", 2 * (2 + len(presets)), spinner=True) as prog:

        def step(msg: str) -> None:
            prog.update(description=msg, advance=1)

        rows = run_experiment1(out, presets=presets, seed=seed, write_pcd=write_pcd,
                               progress=step)
    t = Table(title="Experiment 1 (paper Table 6): surface-sampled stems, no lidar; "
                    "ours (paper)")
    t.add_column("forest", no_wrap=True)
    for col in ("SIC", "stems", "found", "acc. %", "miscl. %", "missed %", "pos RMSE", "SIC s"):
        t.add_column(col, justify="right")

    def p(v: float, ref: float | None) -> str:
        return f"{v:.1f}" if ref is None else f"{v:.1f} ({ref:.1f})"

    for r in rows:
        t.add_row(r.forest, r.preset, str(r.stems), str(r.observed),
                  p(r.accuracy_percent, r.paper_accuracy_percent),
                  p(r.misclassified_percent, r.paper_misclassified_percent),
                  p(r.missed_of_total_percent, r.paper_missed_percent),
                  f"{r.position_rmse_m:.3f} m", f"{r.sic_seconds:.1f}")
    console.print(t)
    console.print(f"Results, plots and clouds: [bold]{out}[/] "
                  f"(summary: {out / 'experiment1.json'})")


@experiment.command("1")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path),
              default=Path("experiment1"), show_default=True, help="Output directory.")
@click.option("--seed", type=click.IntRange(min=0), default=None,
              help="Override the presets' seeds.")
@preset_option("SIC preset(s) to run (default: both).", multiple=True)
@click.option("--no-pcd", is_flag=True, help="Do not write the sampled clouds.")
def experiment_1(out: Path, seed: int | None, presets: tuple[str, ...], no_pcd: bool) -> None:
    """Experiment 1: Forests V and VI surface-sampled, stem algorithm, paper Table 6 beside ours."""
    _experiment1(out, seed, presets or SIC_PRESETS, write_pcd=not no_pcd)


_ROMAN = ["I", "II", "III", "IV", "V", "VI", "VII", "VIII", "IX", "X"]


def parse_forests(text: str) -> list[str]:
    """``I-X``, ``V,VI``, ``II-IV,X``, preset names or TOML paths, comma separated."""
    out: list[str] = []
    for part in (p.strip() for p in text.split(",")):
        if not part:
            continue
        lo, sep, hi = part.partition("-")
        if sep and lo.upper() in _ROMAN and hi.upper() in _ROMAN:
            a, b = _ROMAN.index(lo.upper()), _ROMAN.index(hi.upper())
            if a > b:
                raise click.BadParameter(f"{part!r}: the range runs backwards",
                                         param_hint="--forests")
            out += [f"forest-{r.lower()}" for r in _ROMAN[a:b + 1]]
        elif preset_name(part) is not None and "/" not in part and not part.endswith(".toml"):
            out.append(preset_name(part) or part)
        elif part.endswith(".toml") and Path(part).is_file():
            out.append(part)
        else:
            raise click.BadParameter(
                f"{part!r}: expected roman numerals (I-X, V,VI), a preset "
                f"({', '.join(PRESET_NAMES)}) or a scenario .toml file", param_hint="--forests")
    return list(dict.fromkeys(out))


def parse_modes(text: str) -> list[str]:
    from tcf_hil.experiments.cells import SAMPLED

    modes = [m.strip() for m in text.split(",") if m.strip()]
    bad = [m for m in modes if m not in (*MODES, SAMPLED)]
    if bad or not modes:
        raise click.BadParameter(f"{','.join(bad) or text!r}: allowed modes are "
                                 f"{', '.join(MODES)} and {SAMPLED} (no lidar, Table 9)",
                                 param_hint="--modes")
    return list(dict.fromkeys(modes))


def _progress_sweep(cells: Sequence[Any], out: Path, executor: str, workers: int | None
                    ) -> Any:
    """The sweep with a live display (quiet when stderr is not a terminal): cells done, the
    cells running with their frames and simulation time, and the latest cell's score."""
    from protocols.ouster import parse_mode
    from tcf_hil.experiments.sweep import run_sweep

    announce_backend()
    failures = 0
    running: dict[str, str] = {}  # cell id -> "frames 312/1000, sim 31.2 s"
    ended: set[str] = set()  # (a worker's last report may come after its result)
    lock = threading.Lock()
    latest = ""
    with Progress("cells", len(cells), extra=("failed {task.fields[failed]}",
                                              "{task.fields[live]}"), keep=True,
                  failed=0, live="") as prog:

        def live() -> str:
            shown = [f"{cid} {what}" for cid, what in list(running.items())[:2]]
            more = [f"+{len(running) - 2} more running"] if len(running) > 2 else []
            return " · ".join([*shown, *more, *([latest] if latest else [])])

        def on_event(kind: str, cell: Any, row: dict[str, Any] | None) -> None:
            nonlocal failures, latest
            if kind == "progress":  # (from Dask's event loop thread)
                if row is None:
                    return
                hz = parse_mode(cell.mode)[1] if cell.mode in MODES else 0
                sim = f", sim {row['frames'] / hz:.1f} s" if hz else ""
                with lock:
                    if cell.id not in ended:
                        running[cell.id] = f"frames {row['frames']}/{row['total']}{sim}"
                    prog.update(live=live())
                return
            with lock:
                running.pop(cell.id, None)
                ended.add(cell.id)
            if kind == "failed":
                failures += 1
                prog.print(f"[red]failed[/] {cell.id}: {row and row.get('error')}")
            elif kind == "done" and row is not None:
                prog.print(f"done {cell.id}: wc {row['all_wc']:.1f} % all, "
                           f"{row['seen_wc']:.1f} % seen ({row['cell_s']:.0f} s)")
                latest = f"latest: {cell.id} wc {row['all_wc']:.1f} % all"
            prog.update(advance=1, failed=failures, live=live(),
                        description="cells (skipped: done before)" if kind == "skipped"
                        else "cells")

        if workers is None and any(c.sic != "reference" for c in cells):
            # a SIC command's cell is a live run: emulators and SIC want about two cores
            workers = max(1, (os.cpu_count() or 2) // 2)
        return run_sweep(cells, out, executor=executor, workers=workers, on_event=on_event)


def _print_summary(outcome: Any, out: Path, paths: dict[str, Path]) -> None:
    from tcf_hil.experiments.tables import summary_rows

    t = Table(title="Table 10 layout (mean over seeds; all trees, seen trees)")
    for col in ("forest", "mode", "SIC", "seeds", "wc all %", "wc seen %", "matches",
                "quality err %", "F1"):
        t.add_column(col, justify="left" if col in ("forest", "mode", "SIC") else "right")
    for s in summary_rows(outcome.records):
        t.add_row(s["forest"], s["mode"], s["preset"] or "sic", str(s["seeds"]),
                  f"{s['all_wc_mean']:.1f}", f"{s['seen_wc_mean']:.1f}",
                  f"{s['all_total_matches_mean']:.0f}/{s['stems_mean']:.0f}",
                  f"{s['all_quality_error_percent_mean']:.1f}", f"{s['all_f1_mean']:.3f}")
    console.print(t)
    console.print(f"{outcome.ran} cell(s) run, {outcome.skipped} skipped (done before), "
                  f"{len(outcome.failed)} failed, {outcome.wall_s:.0f} s. "
                  f"Results: [bold]{out / 'results.csv'}[/], tables: {paths['summary.md']}")


def _sweep_options(f: Any) -> Any:
    opts: list[Any] = [
        click.option("--sic", default="reference", show_default=True,
                     help="'reference' (the reference SIC, unpaced and in process on the "
                     "same packet and CAN bytes) or a command run by `tcf-hil run` for every "
                     "cell, live at --speed (see `tcf-hil run --help` for placeholders)."),
        preset_option("Reference SIC preset(s) (default: field). Repeat for several.",
                      multiple=True),
        click.option("--executor", default="local", show_default=True,
                     help="local (a Dask LocalCluster on this machine), dask://HOST:PORT (a "
                     "running scheduler; workers need tcf-hil installed), or inline (this "
                     "process, one cell at a time)."),
        click.option("--workers", type=click.IntRange(min=1), default=None,
                     help="LocalCluster workers (default 2; with a SIC command, one per two "
                     "cores, since each of its cells is a live run)."),
        click.option("--speed", type=click.FloatRange(min=0.05, max=20), default=1.0,
                     show_default=True, help="Pace of a SIC command's live runs."),
        click.option("--keep-pcap", is_flag=True,
                     help="Keep each SIC command run's lidar.pcap (deleted after scoring by "
                     "default: 0.1-1 GB per cell; can.log and the SIC's output stay)."),
        click.option("--frames", type=click.IntRange(min=1), default=None,
                     help="Only the first N lidar frames of each track (quick looks)."),
        sensor_option,
        click.option("--out", type=click.Path(file_okay=False, path_type=Path),
                     required=True, help="Output directory; a rerun skips finished cells."),
    ]
    for opt in reversed(opts):
        f = opt(f)
    return f


def _finish(outcome: Any, out: Path) -> None:
    from tcf_hil.experiments.tables import write_tables

    paths = write_tables(outcome.records, out, outcome.failed)
    _print_summary(outcome, out, paths)
    if outcome.failed:
        err_console.print(f"[red]{len(outcome.failed)} cell(s) failed[/]; their errors are in "
                          f"{paths['summary.md']} and cells/<id>/failed.json; run the same "
                          "command again to retry only them.")
        raise click.exceptions.Exit(1)


@experiment.command("paper")
@click.option("--forests", default="I-X", show_default=True,
              help="Forests: roman ranges and lists (I-X, V,VI), preset names or .toml files.")
@click.option("--modes", default="512x10,1024x10,2048x10", show_default=True,
              help="Lidar modes, comma separated; 'sampled' adds the paper's 1000 points per "
              "stem without lidar (Table 9).")
@click.option("--seeds", type=click.IntRange(min=1, max=1000), default=1, show_default=True,
              help="Seeds per forest and mode (the preset's seed, +1, +2, ...); 3 or more "
              "give 95 % intervals.")
@_sweep_options
def paper_cmd(forests: str, modes: str, seeds: int, sic: str, presets: tuple[str, ...],
              executor: str, workers: int | None, speed: float, keep_pcap: bool,
              frames: int | None, sensor: str | None, out: Path) -> None:
    """The paper's Experiments 2-5 on the wire over Forests I-X.

    Every cell (forest x mode x seed) goes through the whole wire path: the emulator's
    packets and the harvester's CAN frames, the SIC, its JSON, the score against all trees
    and against the trees the sensor saw. Writes OUT/results.csv (one row per cell; columns
    in `tcf-hil experiment columns`), OUT/summary.md (Tables 9/10 with 95 % intervals over
    seeds, Experiment 5's weighting, the paper's reported values), OUT/summary.csv,
    OUT/heatmaps/*.png (Tables 7/8) and OUT/weighting.png (Table 11).

    \b
    Examples:
      tcf-hil experiment paper --forests V,VI --modes 1024x10 --out exp
      tcf-hil experiment paper --seeds 3 --executor dask://10.0.0.5:8786 --out grid
    """
    from tcf_hil.experiments.cells import make_cell
    from tcf_hil.experiments.sweep import parse_executor

    try:
        parse_executor(executor)
    except ValueError as err:
        raise click.BadParameter(str(err), param_hint="--executor") from err
    names = parse_forests(forests)
    mode_list = parse_modes(modes)
    cells = []
    for name in names:
        base = load_scenario(name)
        for k in range(seeds):
            scn = with_sensor(load_scenario(name, seed=base.seed + k), sensor)
            for mode in mode_list:
                for preset in (presets or ("field",)) if sic == "reference" else ("",):
                    cells.append(make_cell(scn, mode, sic=sic, preset=preset or "field",
                                           speed=speed, max_frames=frames,
                                           keep_pcap=keep_pcap))
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    outcome = _progress_sweep(cells, out, executor, workers)
    outcome.wall_s = time.perf_counter() - t0
    _finish(outcome, out)


@experiment.command("passes")
@click.option("--forest", "forest_name", default="V", show_default=True,
              help="The forest (roman numeral, preset or .toml).")
@click.option("--passes", "pass_list", default="1,2,3", show_default=True,
              help="Pass counts to compare, comma separated.")
@click.option("--offset", type=click.FloatRange(min=0), default=None,
              help="Distance between the strip roads, each further pass one road to the left "
              "(m; 0: the same road back in reverse). Default: the scenario's "
              "track.pass_offset_m (strip-road: 20).")
@mode_option()
@click.option("--seeds", type=click.IntRange(min=1, max=1000), default=1, show_default=True)
@_sweep_options
def passes_cmd(forest_name: str, pass_list: str, offset: float | None, mode: str, seeds: int,
               sic: str, presets: tuple[str, ...], executor: str, workers: int | None,
               speed: float, keep_pcap: bool, frames: int | None, sensor: str | None,
               out: Path) -> None:
    """Multi-pass scanning: the same forest driven in 1, 2, 3 ... passes along a strip road.

    Further passes run on further strip roads, --offset to the left (U-turns between
    them), so stems hidden behind others on the first pass come into view. Every pass count
    scans the very same forest: it is cut by as many roads as the largest count needs. The
    table shows the stems seen and the scores against all trees for each pass count: how
    much occlusion the passes remove.

    \b
    Example:
      tcf-hil experiment passes --forest strip-road --passes 1,2,3 --out passes
    """
    from tcf_hil.experiments.cells import make_cell, with_passes

    try:
        counts = sorted({int(p) for p in pass_list.split(",") if p.strip()})
    except ValueError as err:
        raise click.BadParameter(f"{pass_list!r}: expected integers like 1,2,3",
                                 param_hint="--passes") from err
    if not counts or counts[0] < 1 or counts[-1] > 20:
        raise click.BadParameter(f"{pass_list!r}: pass counts from 1 to 20",
                                 param_hint="--passes")
    name = parse_forests(forest_name)[0]
    base = load_scenario(name)
    cells = []
    for k in range(seeds):
        scn = with_sensor(load_scenario(name, seed=base.seed + k), sensor)
        for n in counts:
            multi = with_passes(scn, n, offset, counts[-1])
            for preset in (presets or ("field",)) if sic == "reference" else ("field",):
                cells.append(make_cell(multi, mode, sic=sic, preset=preset, speed=speed,
                                       max_frames=frames, tag=f"p{n}", keep_pcap=keep_pcap))
    out.mkdir(parents=True, exist_ok=True)
    outcome = _progress_sweep(cells, out, executor, workers)
    from tcf_hil.experiments.tables import write_tables

    paths = write_tables(outcome.records, out, outcome.failed)
    t = Table(title=f"Multi-pass scanning, {name}, {mode} (mean over seeds)")
    for col in ("passes", "track s", "stems seen", "matches", "wc all %", "wc seen %",
                "completeness", "F1", "pos RMSE m"):
        t.add_column(col, justify="right")
    by_pass: dict[int, list[dict[str, Any]]] = {}
    for rec in outcome.records:
        r = rec["row"]
        if r["status"] == "ok":
            by_pass.setdefault(int(r["passes"]), []).append(r)
    import numpy as np

    for n in sorted(by_pass):
        rs = by_pass[n]

        def m(k: str, rs: list[dict[str, Any]] = rs) -> float:
            return float(np.mean([float(r[k]) for r in rs]))

        t.add_row(str(n), f"{m('sim_s'):.0f}", f"{m('stems_seen'):.0f}/{m('stems'):.0f}",
                  f"{m('all_total_matches'):.0f}", f"{m('all_wc'):.1f}", f"{m('seen_wc'):.1f}",
                  f"{m('all_completeness'):.3f}", f"{m('all_f1'):.3f}",
                  f"{m('all_position_rmse_m'):.3f}")
    console.print(t)
    console.print(f"Results: [bold]{out / 'results.csv'}[/], tables: {paths['summary.md']}")
    if outcome.failed:
        raise click.exceptions.Exit(1)


@experiment.command("columns")
def columns_cmd() -> None:
    """What every column of results.csv means (a stable contract: columns are appended,
    never reordered)."""
    from tcf_hil.experiments.cells import COLUMNS

    t = Table(title="results.csv columns")
    t.add_column("column", no_wrap=True)
    t.add_column("meaning")
    for c, d in COLUMNS:
        t.add_row(c, d)
    console.print(t)


def _floats_list(text: str, name: str) -> tuple[float, ...]:
    try:
        vals = tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError as err:
        raise click.BadParameter(f"{text!r}: expected numbers like 2,10", param_hint=name) from err
    if not vals or any(not 0.05 <= v <= 100 for v in vals):
        raise click.BadParameter(f"{text!r}: tolerances from 0.05 to 100 mm", param_hint=name)
    return vals


@click.command("bench")
@click.option("--quick", is_flag=True,
              help="Forest II, 512x10, 100 frames, tolerances 2 and 10 mm, both backends and "
              "presets: under a minute (CI runs it).")
@click.option("--forest", "forest_name", default=None, help="Forest (default: V; II quick).")
@click.option("--modes", default=None, help="Lidar modes (default: 512x10,1024x10,2048x10).")
@click.option("--tolerances", default=None,
              help="Stem tessellation tolerances in mm (default: 2,10).")
@click.option("--backends", default=None,
              help="Ray backends (default: embree,open3d; also auto, trimesh).")
@click.option("--presets", default=None, help="Reference SIC presets (default: field,paper).")
@click.option("--frames", type=click.IntRange(min=1), default=None,
              help="Frames per combination (default: 300; 100 quick).")
@click.option("--whole-track", is_flag=True, help="Every frame of the track (overrides --frames).")
@click.option("--seed", type=click.IntRange(min=0), default=None, help="Override the seed.")
@sensor_option
@click.option("--footprints", default=None,
              help="The beam footprint axis: off, adaptive:N, edges:N, full:N (N samples "
              "per FWHM; the sensor's own is adaptive:2; edges: the whole grid at every "
              "edge), comma-separated, e.g. off,adaptive:2,edges:2,full:2 (default: the "
              "sensor's own).")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output directory: bench.md, bench.csv, bench.json, pareto.png.")
def bench_cmd(quick: bool, forest_name: str | None, modes: str | None, tolerances: str | None,
              backends: str | None, presets: str | None, frames: int | None, whole_track: bool,
              seed: int | None, sensor: str | None, footprints: str | None, out: Path) -> None:
    """Speed against error, side by side in one run.

    For every lidar mode x stem tessellation tolerance x beam footprint x ray backend, the
    emulator runs the track once and every reference SIC preset reads the same bytes:
    emulator ms per frame and x real time, the pixels supersampled, the mesh's range error
    and the returns' error (noise, footprint and mesh, as the packets carry them) against
    the exact surfaces, SIC ms per frame (p50/p99), the score (wc, F1), the position and DBH
    RMSE and the DBH bias. Writes a table and a Pareto plot (cost against error).

    \b
    Examples:
      tcf-hil bench --quick --out bench-quick
      tcf-hil bench --modes 1024x10,2048x10 --tolerances 1,2,5,20 --out bench
      tcf-hil bench --forest X --modes 2048x10 --footprints off,adaptive:2,edges:2,full:2
    """
    from tcf_hil.experiments.bench import (
        FULL,
        QUICK,
        BenchGrid,
        footprint_label,
        parse_footprint,
        run_bench,
        tol_label,
        write_bench,
    )

    fps: tuple[str, ...] = ("",)
    if footprints:
        fps = tuple(f.strip() for f in footprints.split(",") if f.strip())
        for f in fps:
            try:
                parse_footprint(f)
            except ValueError as err:
                raise click.BadParameter(str(err), param_hint="--footprints") from err

    g = QUICK if quick else FULL
    grid = BenchGrid(
        forest=parse_forests(forest_name)[0] if forest_name else g.forest,
        modes=tuple(parse_modes(modes)) if modes else g.modes,
        tolerances_mm=_floats_list(tolerances, "--tolerances") if tolerances
        else g.tolerances_mm,
        backends=tuple(b.strip() for b in backends.split(",")) if backends else g.backends,
        presets=tuple(p.strip() for p in presets.split(",")) if presets else g.presets,
        frames=None if whole_track else (frames or g.frames), sensor=sensor, footprints=fps)
    bad = [b for b in grid.backends if b not in BACKEND_CHOICES]
    bad += [p for p in grid.presets if p not in ("field", "tuned", "paper")]
    if bad or "sampled" in grid.modes:
        raise click.BadParameter(f"{', '.join(bad) or 'sampled'}: backends are "
                                 f"{', '.join(BACKEND_CHOICES)}; "
                                 "presets field, tuned, paper; modes lidar modes")
    t0 = time.perf_counter()
    with Progress("bench", spinner=True) as prog:
        rows, notes = run_bench(grid, seed=seed, say=lambda s: prog.update(description=s))
    paths = write_bench(rows, notes, grid, out, time.perf_counter() - t0)
    t = Table(title=f"Speed against error, {grid.forest} "
                    f"({'whole track' if grid.frames is None else f'{grid.frames} frames'})")
    for col in ("mode", "stems", "backend", "preset", "sensor", "footprint", "emu x RT",
                "return p50/p99 mm", "SIC ms p50/p99", "wc seen %", "pos mm", "DBH mm",
                "DBH bias mm"):
        t.add_column(col, justify="left" if col in ("mode", "stems", "backend", "preset",
                                                    "sensor", "footprint") else "right")
    for r in rows:
        t.add_row(r["mode"], tol_label(r), r["backend"], r["preset"], r["sensor"],
                  footprint_label(r), f"{r['emulator_x_realtime']:.1f}",
                  f"{r['return_err_p50_mm']:.1f}/{r['return_err_p99_mm']:.0f}",
                  f"{r['sic_ms_p50']:.1f}/{r['sic_ms_p99']:.1f}", f"{r['wc_seen']:.1f}",
                  f"{r['position_rmse_m'] * 1e3:.1f}", f"{r['dbh_rmse_m'] * 1e3:.1f}",
                  f"{r['dbh_bias_m'] * 1e3:+.1f}")
    console.print(t)
    for n in notes:
        err_console.print(f"[yellow]note[/]: {n}")
    console.print(f"{time.perf_counter() - t0:.0f} s. Table: [bold]{paths['md']}[/], "
                  f"plot: {paths['png']}")
