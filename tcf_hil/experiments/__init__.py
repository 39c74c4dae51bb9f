"""The paper's experiments. Experiment 1 (no lidar) lives here now; the lidar experiments
arrive with the wire."""

from tcf_hil.experiments.experiment1 import PAPER_TABLE6, Experiment1Row, run_experiment1

__all__ = ["PAPER_TABLE6", "Experiment1Row", "run_experiment1"]
