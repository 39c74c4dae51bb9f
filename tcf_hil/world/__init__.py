"""The world a run takes place in: the terrain (:mod:`.terrain`), the harvester's track and the
poses along it (:mod:`.track`), the forest with its exact ground truth (:mod:`.forest`), the
scene the lidar's rays hit and its ray backends (:mod:`.scene`), the faults planned for a run
(:mod:`.faults`), and the exact hits on the true surfaces (:mod:`.analytic`).

May import: :mod:`protocols`, :mod:`emulators` (the compiled kernels and media), the scenario,
and the small shared helpers (``tcf_hil.errors``, ``_io``, ``_rotations``, ``_plots``); never
the devices, recordings, runs or results built on it. Nothing is imported here: each module
is imported where it is needed, so that ``import tcf_hil.world.track`` does not build meshes;
:class:`World` (the world of one run, resolved once) is imported when first asked for.
"""

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from tcf_hil.world._world import World

__all__ = ["World"]


def __getattr__(name: str) -> Any:  # PEP 562: World (and all it imports) only when asked for
    if name == "World":
        from tcf_hil.world._world import World

        return World
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
