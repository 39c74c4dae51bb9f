"""tcf-hil: a hardware-in-the-loop bench for forest-harvester lidar software.

The framework layer: scenarios and the Forest I–X presets, forest generation with exact
ground truth, surface sampling, the evaluation (EE), the reference stem algorithm and the CLI.
Wire formats live in :mod:`protocols`, things that talk on the wire in :mod:`emulators`.
"""

from tcf_hil.errors import ConfigError, InputError, TcfHilError

__version__ = "0.1.0"

__all__ = ["ConfigError", "InputError", "TcfHilError", "__version__"]
