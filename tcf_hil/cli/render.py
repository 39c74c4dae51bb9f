"""``tcf-hil render`` and ``tcf-hil cache``: the render store, filled ahead of a run and
shown or freed."""

from __future__ import annotations

import functools
import os
import time
from datetime import UTC, datetime

import click

from tcf_hil.cli._shared import (
    BACKEND_CHOICES,
    Group,
    Progress,
    announce_backend,
    blame,
    console,
    fault_option,
    mode_option,
    profile_option,
    scenario_with_faults,
    seed_option,
    sensor_option,
)


def _gb(n: int) -> str:
    return f"{n / 1e9:.2f} GB" if n >= 1e8 else f"{n / 1e6:.1f} MB"


@click.command("render")
@click.argument("scenario_name", metavar="SCENARIO")
@mode_option("2048x10")
@profile_option()
@seed_option()
@click.option("--backend", type=click.Choice(BACKEND_CHOICES), default="auto", show_default=True,
              help="Ray casting backend (a run must use the same one to find the render).")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Renderer processes at once, each taking blocks of 10 frames in turn "
                   "(the ray threads shared out among them) [default: one per CPU this "
                   "process may use]; a scenario with fault plans renders in order, in one.")
@click.option("--executor", default="local", show_default=True,
              help="local (renderer processes on this machine, --workers of them), or "
                   "dask://HOST:PORT: blocks of 10 frames as tasks on a running Dask "
                   "scheduler's workers (each builds the scene once; they need the same "
                   "tcf-hil installed; several worker processes on one host: set "
                   "TCF_HIL_RAY_THREADS to their share of its cores), written into this "
                   "machine's store in order. A scenario with fault plans renders locally, "
                   "in order.")
@fault_option
@sensor_option
def render_cmd(scenario_name: str, mode: str, profile: str, seed: int | None, backend: str,
               workers: int | None, executor: str, faults: tuple[str, ...],
               sensor: str | None) -> None:
    """Render SCENARIO's whole track into the render store, ahead of a run.

    \b
    A run of the same scenario, seed, mode, profile, sensor and faults (tcf-hil run, which
    defaults to 2048x10 as this command) then streams every frame from the store at the
    sensor's cadence: the bench only paces and copies, the program under test gets the
    machine, and every such run sends the same bytes. The reference SIC's cells of tcf-hil
    experiment read the same render (of a scene without fault plans: a cell injects none).
    A render cut short (Ctrl-C) keeps its whole frames; the next render goes on from there.
    The store is shown and freed with tcf-hil cache (its root: $TCF_HIL_CACHE, else
    ~/.cache/tcf-hil; at most $TCF_HIL_CACHE_MAX_GB, default 20, least recently used renders
    go first).

    \b
    Example:
      tcf-hil render pine-thinning --mode 1024x10
      tcf-hil run pine-thinning --mode 1024x10 --sic "./my_sic"
      tcf-hil render spruce-final-felling --executor dask://10.0.0.5:8786
    """
    from tcf_hil.devices.dask_render import render_on_dask
    from tcf_hil.devices.lidar import LidarRun
    from tcf_hil.experiments.sweep import parse_executor
    from tcf_hil.recording.store import RenderStore
    from tcf_hil.run import RUN_T0_NS

    try:
        kind, address = parse_executor(executor)
    except ValueError:
        kind, address = "?", None
    if kind not in ("local", "dask"):
        raise click.BadParameter(f"{executor!r}: expected local or dask://HOST:PORT",
                                 param_hint="--executor")
    scn = scenario_with_faults(scenario_name, faults, sensor=sensor)
    announce_backend(backend)
    store = RenderStore()
    with blame(scenario_name):
        run = LidarRun(scn, mode=mode, profile=profile, seed=seed, backend=backend,
                       t0_ns=RUN_T0_NS, store=store, render="stored")
    key = run.render_key
    if address is not None and not run.parallel_render():
        raise click.BadParameter(f"{executor}: {scn.name} has fault plans (or noise drawn "
                                 "frame by frame): it renders in order, here (--executor "
                                 "local)", param_hint="--executor")
    if address is not None and workers is not None:
        raise click.BadParameter("--workers is for --executor local (a Dask cluster has its "
                                 "own workers)", param_hint="--workers")
    if run.stored is not None:
        console.print(f"{scn.name} {mode} {profile}: already stored ({key}, "
                      f"{run.stored.frames} frames)")
        return
    t0 = time.perf_counter()
    with blame(scenario_name), Progress(f"render {scn.name} {mode}") as bar:
        made = run.render_into_store(progress=bar.counter,
                                     workers=workers or len(os.sched_getaffinity(0)),
                                     remote=None if address is None else
                                     functools.partial(render_on_dask, address=address))
    wall = time.perf_counter() - t0
    sim = made / run.meta.frequency_hz
    info = next(e for e in store.entries() if e["key"] == key)
    console.print(f"{scn.name} {mode} {profile}: {made} frames rendered in {wall:.1f} s "
                  f"({sim / wall if wall else 0:.2f}x real time), {_gb(info['bytes'])} in "
                  f"{store.path(key or '')}")


@click.group("cache", cls=Group)
def cache() -> None:
    """The render store (tcf-hil render): list what it holds, free it."""


@cache.command("list")
def cache_list() -> None:
    """Every render in the store, most recently used first, with its size."""
    from rich.table import Table

    from tcf_hil.recording.store import RenderStore

    store = RenderStore()
    es = store.entries()
    if not es:
        console.print(f"the render store ({store.root}) is empty")
        return
    t = Table(title=f"render store {store.root} (limit {_gb(store.max_bytes)})")
    for col in ("key", "scenario", "mode", "seed", "frames", "size", "last used"):
        t.add_column(col)
    for e in es:
        m = e["made_of"]
        sens = m.get("sensor", {})
        used = datetime.fromtimestamp(e["used_unix"], UTC).strftime("%Y-%m-%d %H:%M")
        frames = f"{e['frames']}/{e['frames_total']}" + ("" if e["complete"] else " (partial)")
        t.add_row(e["key"], str(m.get("scenario", {}).get("name", "?")),
                  f"{sens.get('mode', '?')} {sens.get('profile', '')}", str(m.get("seed", "?")),
                  frames, _gb(e["bytes"]), used)
    console.print(t)
    console.print(f"{len(es)} renders, {_gb(sum(e['bytes'] for e in es))}")


@cache.command("clear")
@click.option("--key", "keys", multiple=True, help="Free only this render (repeatable).")
def cache_clear(keys: tuple[str, ...]) -> None:
    """Free the render store (or the renders --key names)."""
    from tcf_hil.recording.store import RenderStore

    store = RenderStore()
    if keys:
        known = {e["key"]: e["bytes"] for e in store.entries()}
        for k in keys:
            if k not in known:
                raise click.BadParameter(f"{k}: no such render (see tcf-hil cache list)",
                                         param_hint="--key")
        for k in keys:
            store.remove(k)
        console.print(f"freed {len(keys)} renders, {_gb(sum(known[k] for k in keys))}")
        return
    n, size = store.clear()
    console.print(f"freed {n} renders, {_gb(size)} ({store.root})")
