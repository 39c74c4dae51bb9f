"""The ``tcf-hil`` command line. Commands stay thin: they parse options and call the library.

One module per command group (:mod:`.run`, :mod:`.lidar`, :mod:`.harvester`,
:mod:`.forest`, :mod:`.score`, :mod:`.export`, :mod:`.experiment`); what they share
(options built from the protocol tables, the progress display, the graceful stop) is in
:mod:`._shared`; the one mapping from errors to exit statuses is :func:`main` here.

Exit status: 0 success, 1 bad input or configuration (one ``Error:`` line naming the file or
key), 2 usage error, 3 the run or check failed (the SIC failed; a soak lost frames or grew),
4 internal error (rerun with ``--traceback`` to see it), 130 stopped by Ctrl-C/SIGTERM.
"""

from __future__ import annotations

import signal
import sys
import threading
import traceback

import click

from tcf_hil import __version__
from tcf_hil.cli import experiment, export, forest, harvester, lidar, render, run, score
from tcf_hil.cli._shared import ExitStatus, Group, err_console, terminate
from tcf_hil.errors import TcfHilError

__all__ = ["cli", "main"]


@click.group(cls=Group, context_settings={"help_option_names": ["-h", "--help"],
                                          "max_content_width": 100})
@click.version_option(__version__, prog_name="tcf-hil")
@click.option("--traceback", is_flag=True, help="Show the full traceback of an internal error.")
@click.pass_context
def cli(ctx: click.Context, traceback: bool) -> None:
    """tcf-hil: a hardware-in-the-loop test bench for forest-harvester lidar software.

    \b
    Start here:
      tcf-hil demo                          the main job: a live run of the reference SIC
      tcf-hil run forest-v --sic "./my_sic --port {lidar_port}"   your onboard program
      tcf-hil render pine-thinning          render a heavy scene ahead: its runs are real time
      tcf-hil scenario list                 the paper's Forests I-X
      tcf-hil forest generate forest-v --out forest-v/
      tcf-hil score ground_truth.json observed.json --plots plots/
      tcf-hil export runs/RUN --out cloud.laz   the cloud and stems for GIS tools

    \b
    Exit status: 0 success, 1 bad input or configuration, 2 usage error, 3 the run or
    check failed, 4 internal error, 130 stopped by Ctrl-C.
    """
    ctx.obj = {"traceback": traceback}


# the teaching order of `tcf-hil --help`
for _cmd in (run.demo, run.run_cmd, run.replay_cmd, run.sic_cmd, render.render_cmd,
             render.cache, forest.scenario, forest.forest, score.detect, score.score,
             export.export_cmd, lidar.lidar, harvester.harvester, run.soak_cmd,
             harvester.can_server, experiment.experiment, experiment.bench_cmd):
    cli.add_command(_cmd)


def main(argv: list[str] | None = None) -> int:
    """Console entry point: maps errors to exit statuses (see the module docstring)."""
    args = sys.argv[1:] if argv is None else argv
    if threading.current_thread() is not threading.main_thread():
        return _main(args)
    # kill / a service manager stops a server or stream as Ctrl-C does: cleanly
    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        return _main(args)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _main(args: list[str]) -> int:
    from tcf_hil._logs import library_logs

    try:
        with library_logs(None):  # python-can's and canopen's warnings off the terminal
            # not standalone, click returns the status of a command that ended with
            # click.exceptions.Exit (ctx.exit, _shared.finish) instead of raising it
            status = cli.main(args=args, prog_name="tcf-hil", standalone_mode=False)
    except click.exceptions.Abort:
        err_console.print("Aborted.")
        return ExitStatus.BAD_INPUT
    except click.ClickException as err:
        err.show()
        return err.exit_code
    except click.exceptions.Exit as err:
        return err.exit_code
    except TcfHilError as err:
        click.echo(f"Error: {err}", err=True)
        return ExitStatus.BAD_INPUT
    except KeyboardInterrupt:
        click.echo("Interrupted.", err=True)
        return ExitStatus.INTERRUPTED
    except Exception:
        if "--traceback" in args:
            traceback.print_exc()
        else:
            exc = sys.exc_info()[1]
            click.echo(f"Internal error: {type(exc).__name__}: {exc} "
                       "(rerun with --traceback and report it)", err=True)
        return ExitStatus.INTERNAL
    return status if isinstance(status, int) else ExitStatus.OK
