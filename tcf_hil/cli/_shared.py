"""What the commands share: the consoles, options built once from the protocol tables, one
progress display, one graceful stop, and the exit status of a run."""

from __future__ import annotations

import contextlib
import datetime as _dt
import signal
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

import click
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    ProgressColumn,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.progress import Progress as _RichProgress

from protocols.ouster import EMULATED_PROFILES, OS0_64_MODES
from tcf_hil.errors import ConfigError
from tcf_hil.sic import PRESETS

console = Console(soft_wrap=True)
err_console = Console(stderr=True)

Decorator = Callable[[Callable[..., Any]], Callable[..., Any]]


class Group(click.Group):
    """Lists its commands in the order they were added (the teaching order)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(self.commands)


# ------------------------------------------------------------------------------ options
MODES: tuple[str, ...] = OS0_64_MODES
PROFILE_NAMES: tuple[str, ...] = ("RNG19_RFL8_SIG16_NIR16", *sorted(
    p for p in EMULATED_PROFILES if p != "RNG19_RFL8_SIG16_NIR16"))
BACKEND_CHOICES: tuple[str, ...] = ("auto", "embree", "open3d", "trimesh")
"""Ray backends by name (:data:`tcf_hil.world.scene.BACKENDS` and ``auto``; a test holds the two
together without importing the scene here, which would slow every command's start)."""
_announced: set[str] = set()


def announce_backend(name: str = "auto") -> None:
    """Say once per process which ray backend ``auto`` took, where it is not Embree (e.g.
    ``ray backend: open3d (embreex is not installed here: Embree has no wheel for aarch64)``).
    A named backend that is missing is the ConfigError its scene raises."""
    from tcf_hil.world.scene import resolve_backend

    if name in _announced:
        return
    _announced.add(name)
    note = resolve_backend(name)[1]
    if note is not None:
        err_console.print(f"[yellow]{note}[/]")


SIC_PRESETS: tuple[str, ...] = tuple(sorted(PRESETS, key=lambda p: (p != "field", p)))


def mode_option(default: str = "1024x10", **kw: Any) -> Decorator:
    return click.option("--mode", type=click.Choice(MODES), default=default, show_default=True,
                        help=kw.pop("help", "Columns x frames per second."), **kw)


def profile_option() -> Decorator:
    return click.option("--profile", type=click.Choice(PROFILE_NAMES),
                        default="RNG19_RFL8_SIG16_NIR16", show_default=True,
                        help="UDP lidar profile.")


def preset_option(help: str = "The reference SIC's parameters.", *, multiple: bool = False
                  ) -> Decorator:
    if multiple:
        return click.option("--preset", "presets", type=click.Choice(SIC_PRESETS),
                            multiple=True, help=help)
    return click.option("--preset", type=click.Choice(SIC_PRESETS), default="field",
                        show_default=True, help=help)


def seed_option(help: str = "Override the seed.") -> Decorator:
    return click.option("--seed", type=click.IntRange(min=0), default=None, help=help)


def run_dir_option(what: str = "Run directory (default ./runs/<UTC time stamp>/).") -> Decorator:
    return click.option("--out", type=click.Path(file_okay=False, path_type=Path),
                        default=None, help=what)


_FAULT_HELP = ("Inject a fault: KEY=VALUE below the scenario's [faults] (repeatable), e.g. "
               "udp.loss=0.01, udp.burst_rate=0.001, udp.jitter_us=200, udp.reorder=0.01, "
               "lidar.dropout=0.02, lidar.reinit_at_s=[30], can.loss=0.01, "
               "can.pose_delay_ms=50, can.bus_off_at_s=[20], can.nmt_reset_at_s=[40]. "
               "`tcf-hil scenario show NAME` lists every key.")


def fault_option(f: Callable[..., Any]) -> Callable[..., Any]:
    return click.option("--fault", "faults", multiple=True, metavar="KEY=VALUE",
                        help=_FAULT_HELP)(f)


def floats(n: int, names: str) -> Callable[[click.Context, click.Parameter, Any], Any]:
    """A click callback: ``n`` comma-separated numbers."""

    def convert(_ctx: click.Context, param: click.Parameter, value: Any) -> Any:
        if value is None:
            return None
        try:
            parts = tuple(float(v) for v in str(value).split(","))
        except ValueError as err:
            raise click.BadParameter(f"{value!r}: expected {n} comma-separated numbers "
                                     f"({names})", param=param) from err
        if len(parts) != n:
            raise click.BadParameter(f"{value!r}: expected {n} comma-separated numbers "
                                     f"({names})", param=param)
        return parts
    return convert


def run_dir(out: Path | None, prefix: str = "") -> Path:
    """``out``, or ./runs/<prefix><UTC time stamp>/."""
    return out or Path("runs") / (prefix + _dt.datetime.now(_dt.UTC).strftime("%Y%m%dT%H%M%SZ"))


@contextlib.contextmanager
def blame(scenario_name: str) -> Iterator[None]:
    """Name the scenario in a configuration error found only while building its forest."""
    try:
        yield
    except ConfigError as err:
        if err.source is not None:
            raise
        raise ConfigError(err.key, err.value, err.allowed, scenario_name) from err


def scenario_with_faults(name: str, faults: Sequence[str], seed: int | None = None,
                         sensor: str | None = None) -> Any:
    """The scenario with the --fault options applied and the --sensor preset (None: its
    own ``[sensor]``)."""
    from tcf_hil.devices.faults import apply_fault_options
    from tcf_hil.scenario import load_scenario, with_sensor

    return with_sensor(apply_fault_options(load_scenario(name, seed=seed), faults), sensor)


SENSOR_NAMES: tuple[str, ...] = ("os0-64-rev7", "os0-64-rev6", "ideal")
"""The sensor presets (:data:`emulators.lidar.SENSOR_PRESETS`; a test holds them together
without importing the emulator here)."""


def sensor_option(f: Callable[..., Any]) -> Callable[..., Any]:
    """--sensor PRESET: the lidar's physics, over the scenario's own ``[sensor]``."""
    return click.option(
        "--sensor", "sensor", type=click.Choice(SENSOR_NAMES), default=None,
        help="Sensor physics preset instead of the scenario's [sensor] (os0-64-rev7 unless "
        "it says otherwise): os0-64-rev7 (beam footprint, noise, reach by reflectance), "
        "os0-64-rev6, or ideal (exact pencil rays, no noise).")(f)


# ----------------------------------------------------------------------------- progress
class Progress:
    """The one progress display: [spinner] description, bar, done/total, ``extra`` text
    columns (``{task.fields[NAME]}``), elapsed and remaining time, on stderr. Quiet when
    stderr is not a terminal. ``keep``: leave the last state on screen; ``counts``: show
    done/total."""

    def __init__(self, description: str, total: float | None = None, *,
                 extra: Sequence[str] = (), spinner: bool = False, keep: bool = False,
                 counts: bool = True, **fields: Any) -> None:
        cols: list[str | ProgressColumn] = [SpinnerColumn()] if spinner else []
        cols += [TextColumn("{task.description}"), BarColumn()]
        cols += [MofNCompleteColumn()] if counts else []
        cols += [TextColumn(e) for e in extra]
        cols += [TimeElapsedColumn(), TimeRemainingColumn()]
        self._rich = _RichProgress(*cols, console=err_console, transient=not keep,
                                   disable=not err_console.is_terminal)
        self._task = self._rich.add_task(description, total=total, **fields)

    def __enter__(self) -> Progress:
        self._rich.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._rich.__exit__(*exc)  # type: ignore[arg-type]

    def update(self, **kw: Any) -> None:
        """``completed``, ``total``, ``advance``, ``description`` or a field."""
        self._rich.update(self._task, **kw)

    def counter(self, done: int, total: int) -> None:
        """A ``progress(done, total)`` callback."""
        self._rich.update(self._task, completed=done, total=total)

    def print(self, text: str) -> None:
        """A line above the display."""
        self._rich.console.print(text)


class LiveRun:
    """The live display of a run (``run``, ``replay``, ``soak``): what it is doing, a bar of
    simulation time, then simulation time, frames sent and lost, CAN poses, publications and
    the latest score (:meth:`tcf_hil.run.LiveFigures.line`), elapsed and remaining time; on
    stderr, four times a second. Quiet when stderr is not a terminal: :attr:`watch` is then
    None, so the run gathers nothing and computes no live score."""

    def __init__(self, what: str) -> None:
        self.active = err_console.is_terminal
        self._bar = Progress(what, extra=("{task.fields[line]}",), spinner=True, counts=False,
                             line="")

    def __enter__(self) -> LiveRun:
        self._bar.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._bar.__exit__(*exc)

    @property
    def watch(self) -> Callable[[Any], None] | None:
        return self._show if self.active else None

    def _show(self, fig: Any) -> None:
        self._bar.update(description=fig.phase, completed=fig.sim_s or 0.0,
                         total=fig.sim_total_s, line=fig.line())

    def counter(self, done: int, total: int, unit: str = "MB") -> None:
        """A ``progress(done, total)`` callback for a step before the run (checking a
        recording): said in the line (the bar is the run's simulation time; a looping replay
        has no total, and rich keeps a total once given)."""
        self._bar.update(line=f"{done}/{total} {unit}")

    def phase(self, what: str) -> None:
        self._bar.update(description=what)


# -------------------------------------------------------------------------------- stops
def terminate(_sig: int, _frame: object) -> None:
    """SIGTERM as Ctrl-C: a service manager stops a command as a person does."""
    raise KeyboardInterrupt


@contextlib.contextmanager
def graceful_stop(what: str) -> Iterator[threading.Event]:
    """The first Ctrl-C or SIGTERM sets the event and says ``what`` happens now (the command
    finishes cleanly); the second aborts (KeyboardInterrupt). Handlers are restored after."""
    stop = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield stop  # signals reach the main thread only
        return

    def first(_sig: int, _frame: object) -> None:
        err_console.print(f"{what} (Ctrl-C again aborts)")
        stop.set()
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, terminate)

    previous = signal.signal(signal.SIGINT, first)
    previous_term = signal.signal(signal.SIGTERM, first)
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)
        signal.signal(signal.SIGTERM, previous_term)


# ------------------------------------------------------------------------- exit status
class ExitStatus:
    """The documented exit statuses (README, `tcf-hil --help`)."""

    OK = 0
    BAD_INPUT = 1  # bad input or configuration; one ``Error:`` line
    USAGE = 2  # click's usage errors
    FAILED = 3  # the run or check failed: the SIC failed, a soak lost frames or grew
    INTERNAL = 4  # an internal error (--traceback shows it)
    INTERRUPTED = 130  # stopped by Ctrl-C / SIGTERM


def finish(code: int) -> None:
    """End the command with ``code`` through click (the one error-to-exit mapping)."""
    if code:
        raise click.exceptions.Exit(code)
