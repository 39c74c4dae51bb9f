"""The faults a run is to suffer: the scenario's ``[faults]`` section turned into the emulators'
fault plans (UDP loss, bursts, duplicates, reordering and jitter; lidar dropouts and
re-inits; CAN loss, delay, bus-off and NMT resets), seeded from ``[faults] seed`` or the run's
seed, at simulation times on the run's track. Built once per run, in its
:class:`~tcf_hil.world.World`; what was injected is logged by :mod:`tcf_hil.devices.faults`."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from emulators.faults import CanFaultPlan, LidarFaultPlan, UdpFaults
from tcf_hil.scenario import FaultsConfig

__all__ = ["FaultPlans", "fault_plans", "faults_active"]


def faults_active(cfg: FaultsConfig) -> bool:
    """Whether the section asks for any fault."""
    return cfg != FaultsConfig(seed=cfg.seed)


@dataclass
class FaultPlans:
    udp: UdpFaults | None
    lidar: LidarFaultPlan | None
    can: CanFaultPlan | None


def fault_plans(cfg: FaultsConfig, run_seed: int, track_t0_ns: int, lidar_port: int = 7502,
                imu_port: int = 7503) -> FaultPlans:
    """The plans of a run whose track starts at ``track_t0_ns`` (None where nothing is asked)."""
    seed = cfg.seed or run_seed

    def at(seconds: Iterable[float]) -> tuple[int, ...]:
        return tuple(track_t0_ns + round(s * 1e9) for s in sorted(seconds))

    u = cfg.udp
    ports = {"both": (), "lidar": (lidar_port,), "imu": (imu_port,)}[u.ports]
    udp = UdpFaults(u.loss, u.burst_rate, u.burst_packets, u.duplicate, u.reorder, u.jitter_us,
                    ports, seed)
    li = cfg.lidar
    lidar = LidarFaultPlan(li.dropout, at(li.dropout_at_s), li.dropout_frames,
                           at(li.reinit_at_s), round(li.reinit_gap_s * 1e9), seed)
    c = cfg.can
    can = CanFaultPlan(c.loss, round(c.pose_delay_ms * 1e6), at(c.bus_off_at_s),
                       round(c.bus_off_s * 1e9), at(c.nmt_reset_at_s),
                       round(c.nmt_restart_s * 1e9), seed)
    return FaultPlans(udp if udp.active else None, lidar if lidar.active else None,
                      can if can.active else None)
