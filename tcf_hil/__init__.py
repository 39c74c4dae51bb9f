"""tcf-hil: a hardware-in-the-loop bench for forest-harvester lidar software.

The framework layer, one package per subsystem, each importing only those listed before it
(``tests/test_layers.py`` holds them to that order, with no import circles and no private
name taken from another module):

- :mod:`tcf_hil.scenario`: scenario files and the Forest I–X and natural-stand presets;
- :mod:`tcf_hil.world`: terrain, track, forest with exact ground truth, scene and ray backends;
- :mod:`tcf_hil.recording`: what crossed the wire read back; stems documents; inventories;
- :mod:`tcf_hil.evaluation`: matching, metrics, the scoring of a forest (once per run);
- :mod:`tcf_hil.devices`: the OS0-64 and the harvester as a run composes them, faults, endpoints;
- :mod:`tcf_hil.results`: the HTML report and the exports;
- :mod:`tcf_hil.run`: the session, live and replay traffic, the SIC's process, the recorder, soak;
- :mod:`tcf_hil.sic`: the reference onboard program (it talks to the rest only on the wire);
- :mod:`tcf_hil.experiments`: the paper's experiments, sweeps and benches;
- :mod:`tcf_hil.cli`: the ``tcf-hil`` command.

Small shared helpers sit beside them (``errors``, ``_io``, ``_crc``, ``_rotations``,
``_plots``, ``_logs``). Wire formats live in :mod:`protocols`, things that talk on the wire in
:mod:`emulators`.
"""

from tcf_hil.errors import ConfigError, InputError, TcfHilError

__version__ = "0.1.0"

__all__ = ["ConfigError", "InputError", "TcfHilError", "__version__"]
