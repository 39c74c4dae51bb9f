"""A run's world is resolved once (:class:`tcf_hil.world.World`) and every device takes it:
the lidar and the harvester node drive the same track object, the fault plans are built
once with the run's ports, the scene is built once per backend, and a natural stand's
scenery asks its forest for the track instead of building its own."""

from __future__ import annotations

import pytest

from tcf_hil.devices.harvester import HarvesterModel
from tcf_hil.devices.lidar import LidarRun
from tcf_hil.scenario import load_scenario, scenario_from_dict, scenario_to_dict
from tcf_hil.world import World
from tcf_hil.world.track import Trajectory


@pytest.fixture(scope="module")
def faulty():
    d = scenario_to_dict(load_scenario("forest-i"))
    d["faults"] = {"udp": {"loss": 0.01, "ports": "lidar"}, "can": {"loss": 0.02}}
    return scenario_from_dict(d)


def test_every_device_takes_the_one_world(faulty, monkeypatch: pytest.MonkeyPatch) -> None:
    built: list[int] = []
    real = Trajectory.from_config.__func__  # type: ignore[attr-defined]

    def counting(cls, *a, **k):  # type: ignore[no-untyped-def]
        built.append(1)
        return real(cls, *a, **k)

    monkeypatch.setattr(Trajectory, "from_config", classmethod(counting))
    w = World.build(faulty, seed=5, t0_ns=60_000_000_000, lidar_ports=(41000, 41001))
    assert w.seed == 5 == w.forest.seed and w.t0_ns == 60_000_000_000
    run = LidarRun(faulty, mode="512x10", world=w, udp_port_lidar=41000, udp_port_imu=41001)
    node = HarvesterModel.from_world(w)
    assert run.track is w.track and node.trajectory is w.track and run.forest is w.forest
    assert run.scene is w.scene() and w.scene() is w.scene("auto")  # once per backend
    assert built == [1], "the track was built more than once"
    assert w.faults is not None and w.faults.udp is not None and w.faults.can is not None
    assert w.faults.udp.ports == (41000,)  # the run's lidar port, not the default
    assert run.udp_faults is w.faults.udp


def test_a_world_of_its_own_where_none_is_given(faulty) -> None:
    run = LidarRun(faulty, mode="512x10", seed=3)
    assert run.world.seed == 3 and run.world.forest is run.forest
    assert World.build(load_scenario("forest-i")).faults is None  # no [faults]: no plans


def test_the_scenery_asks_its_forest_for_the_track() -> None:
    forest = World.build(load_scenario("forest-i")).forest
    assert forest.track() is forest.track()


def test_a_run_opens_its_traffic_from_its_source(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """A scenario is live traffic; a path is a recording, read (and checked) as it opens."""
    from tcf_hil.errors import InputError
    from tcf_hil.run import LiveTraffic, open_traffic

    live = open_traffic(load_scenario("forest-i"), mode="512x10", speed=2.0)
    assert isinstance(live, LiveTraffic) and live.speed == 2.0
    with pytest.raises(InputError, match="not a tcf-hil run directory"):
        open_traffic(tmp_path)  # an empty directory: not a recording


def test_a_run_cut_short_stands_where_it_stopped_on_can_too() -> None:
    """After the run's last frame the node publishes the machine standing there: the same
    pose, each stamped with its own time (a SIC's pose track must go on), at speed 0."""
    from tcf_hil.devices.harvester import standing_from

    w = World.build(load_scenario("forest-ii"), t0_ns=60_000_000_000)
    model = HarvesterModel.from_world(w)
    stop = w.t0_ns + 3_000_000_000  # three seconds into the drive
    pose = standing_from(model.bus_pose, stop)
    assert pose(stop - 10_000_000) == model.bus_pose(stop - 10_000_000)
    later = [pose(stop + k * 10_000_000) for k in range(1, 4)]
    assert [p.time_us for p in later] == [(stop + k * 10_000_000) // 1000 for k in (1, 2, 3)]
    moving = model.bus_pose(stop)
    assert moving.speed_m_s > 0.1
    assert all((p.x_m, p.y_m, p.heading_deg, p.speed_m_s) ==
               (moving.x_m, moving.y_m, moving.heading_deg, 0.0) for p in later)
