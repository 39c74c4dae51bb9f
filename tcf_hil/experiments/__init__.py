"""The paper's experiments: Experiment 1 (no lidar), and sweeps of cells on the wire (Dask),
the tables, multi-pass scanning and the speed-against-error bench.

Nothing heavy is imported here: the command line (:mod:`tcf_hil.cli.experiment`) imports
what a command needs when it runs.
"""

from __future__ import annotations

from typing import Any

__all__ = ["PAPER_TABLE6", "Experiment1Row", "run_experiment1"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from tcf_hil.experiments import experiment1

        return getattr(experiment1, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
