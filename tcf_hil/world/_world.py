"""A run's world, resolved once: the scenario, its seed, the forest with its ground truth, the
track with its start time, the fault plans and (when first asked for) the scene of each ray
backend. Every device of the run, the recorder and the results take this one object, so
nothing is built twice and nothing can disagree: ``tcf-hil run`` built the track three times
(the lidar, and the harvester node twice), the fault plans twice and resolved the seed's
default in three places before it."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from tcf_hil.scenario import Scenario
from tcf_hil.world.faults import FaultPlans, fault_plans, faults_active
from tcf_hil.world.forest import Forest, generate_forest
from tcf_hil.world.track import Trajectory

if TYPE_CHECKING:
    from tcf_hil.world.scene import Scene

__all__ = ["World"]


@dataclass(frozen=True)
class World:
    """What a run takes place in (:meth:`build` makes one). One world serves one run: the
    fault plans carry their draws' state as they are used, so a second run in the same
    process builds a world of its own (or its faults would go on where the first left)."""

    scenario: Scenario
    seed: int  # the run's seed: the scenario's unless the run names one
    forest: Forest
    track: Trajectory  # the harvester's path, starting at ``track.t0_ns`` (simulation ns)
    faults: FaultPlans | None  # None: the scenario asks for no fault
    lidar_ports: tuple[int, int]  # the UDP ports the fault plans' port filters name
    _scenes: dict[str, Scene] = field(default_factory=dict, repr=False, compare=False)

    @classmethod
    def build(cls, scn: Scenario, *, seed: int | None = None, t0_ns: int = 1_000_000_000,
              forest: Forest | None = None, lidar_ports: tuple[int, int] = (7502, 7503)
              ) -> World:
        """The world of ``scn`` with ``seed`` (default: the scenario's), its track starting
        at ``t0_ns``. ``forest``: one built by the caller (hand-placed stems, say) instead of
        the one the scenario generates; its seed is the run's. ``lidar_ports``: the lidar and
        IMU ports the UDP faults apply to."""
        forest = forest if forest is not None else generate_forest(scn, seed)
        track = Trajectory.from_config(scn.track, forest.terrain, t0_ns)
        plans = (fault_plans(scn.faults, forest.seed, t0_ns, *lidar_ports)
                 if faults_active(scn.faults) else None)
        return cls(scn, forest.seed, forest, track, plans, lidar_ports)

    @property
    def t0_ns(self) -> int:
        return self.track.t0_ns

    def scene(self, backend: str = "auto") -> Scene:
        """The scene the lidar's rays hit, on ``backend`` (built once per backend)."""
        from tcf_hil.world.scene import Scene

        if backend not in self._scenes:
            self._scenes[backend] = Scene.from_forest(self.forest, backend=backend)
        return self._scenes[backend]
