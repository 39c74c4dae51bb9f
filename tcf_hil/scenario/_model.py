"""Typed, frozen scenario objects.

Every field carries its unit in its name and its limits in ``metadata``; the loader in
:mod:`tcf_hil.scenario._load` validates a TOML document against these classes, so this file is
the one place that says what a scenario may contain.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Literal

from emulators.lidar import DEFAULT_SENSOR, SENSOR_PRESETS, SensorModel

"""Stem classes: S straight, C curved (sweep), X other (crooked beyond the C limit)."""


def _f(default: Any, doc: str, **limits: Any) -> Any:
    """A dataclass field with its documentation and limits (ge, gt, le) as metadata."""
    return field(default=default, metadata={"doc": doc, **limits})


@dataclass(frozen=True, slots=True)
class PlotConfig:
    size_m: tuple[float, float] = _f(
        (100.0, 100.0), "plot extent along x and y, centred on the local origin", gt=0.0)
    origin_m: tuple[float, float, float] = _f(
        (0.0, 0.0, 0.0), "geographic origin (e.g. UTM easting, northing, height) added to "
        "every world coordinate written out")


@dataclass(frozen=True, slots=True)
class TerrainConfig:
    kind: Literal["flat", "rolling"] = _f("flat", "terrain shape")
    elevation_m: float = _f(0.0, "mean ground height")
    amplitude_m: float = _f(
        1.0, "rolling: height of a typical bump (RMS height is amplitude/sqrt 2)",
        ge=0.0, le=100.0)
    wavelength_m: float = _f(
        40.0, "rolling: wavelength of the largest octave", gt=0.5, le=10000.0)
    octaves: int = _f(4, "rolling: number of noise octaves", ge=1, le=10)
    persistence: float = _f(
        0.5, "rolling: amplitude ratio between octaves", gt=0.0, le=1.0)
    waves_per_octave: int = _f(
        6, "rolling: random plane waves summed per octave", ge=1, le=64)
    margin_m: float = _f(
        20.0, "terrain mesh extends this far beyond the plot", ge=0.0, le=1000.0)
    tolerance_mm: float = _f(
        20.0, "terrain mesh: maximum height error between grid vertices", gt=0.0)
    slope_deg: float = _f(
        0.0, "tilts the whole terrain into a hillside this steep (any kind)", ge=0.0, le=60.0)
    uphill_azimuth_deg: float = _f(
        0.0, "compass direction the hillside rises toward (0 north, 90 east)", ge=-360.0,
        le=360.0)
    roughness_m: float = _f(
        0.0, "micro-relief: RMS height of short waves over any kind of terrain (0: none)",
        ge=0.0, le=1.0)
    roughness_wavelength_m: float = _f(
        2.0, "micro-relief: typical wavelength (0.7-1.4 of it)", ge=0.3, le=50.0)


@dataclass(frozen=True, slots=True)
class DbhConfig:
    kind: Literal["fixed", "normal", "uniform", "lognormal", "weibull"] = _f(
        "normal", "DBH distribution (weibull: two-parameter, its shape and scale matched to "
        "mean_m and sd_m)")
    mean_m: float = _f(0.25, "mean DBH (fixed: the value)", gt=0.0, le=3.0)
    sd_m: float = _f(0.02, "standard deviation (normal, lognormal)", ge=0.0)
    min_m: float = _f(0.12, "smallest DBH (also uniform's low end)", gt=0.0)
    max_m: float = _f(0.45, "largest DBH (also uniform's high end)", gt=0.0)


@dataclass(frozen=True, slots=True)
class ClassMix:
    S: float = _f(0.5, "share (or count) of straight stems", ge=0.0)
    C: float = _f(0.4, "share (or count) of curved stems", ge=0.0)
    X: float = _f(0.1, "share (or count) of other (crooked) stems", ge=0.0)


@dataclass(frozen=True, slots=True)
class SweepConfig:
    S: tuple[float, float] = _f(
        (0.0, 0.02), "maxcurve range drawn for S stems, m", ge=0.0)
    C: tuple[float, float] = _f(
        (0.08, 0.20), "maxcurve range drawn for C stems, m", ge=0.0)
    X: tuple[float, float] = _f(
        (0.30, 0.50), "maxcurve range drawn for X stems, m", ge=0.0)


@dataclass(frozen=True, slots=True)
class StemsConfig:
    count: int = _f(550, "number of stems", ge=0, le=10_000_000)
    height_m: tuple[float, float] = _f(
        (11.0, 27.0), "stem height range (uniform)", gt=1.5, le=150.0)
    dbh: DbhConfig = field(default_factory=DbhConfig, metadata={"doc": "DBH distribution"})
    taper_exponent: float = _f(
        0.8, "radius ~ (distance to top)^exponent; 1 is a cone", gt=0.0, le=3.0)
    top_diameter_m: float = _f(0.03, "diameter at the top", ge=0.0, le=1.0)
    class_mix: ClassMix = field(default_factory=ClassMix,
                                metadata={"doc": "class shares; normalised to count"})
    curve_threshold_m: float = _f(
        0.05, "maxcurve at or above this is curved (C)", gt=0.0)
    other_threshold_m: float = _f(
        0.25, "maxcurve at or above this is other (X)", gt=0.0)
    sweep_m: SweepConfig = field(default_factory=SweepConfig,
                                 metadata={"doc": "maxcurve drawn per class"})
    lean_deg: tuple[float, float] = _f(
        (0.0, 0.0), "lean from vertical, uniform range (paper: upright)", ge=0.0, le=30.0)
    tolerance_mm: float = _f(
        2.0, "stem mesh: maximum chord error (sets sides and ring spacing), where stems are "
        "meshes (stems.geometry)", gt=0.01, le=100.0)
    geometry: Literal["auto", "curves", "mesh"] = _f(
        "auto", "stems and branches as exact round curves (Embree cast from compiled "
        "kernels), as meshes (any backend), or auto: curves where the backend casts them")
    below_ground_m: float = _f(
        0.5, "stem meshes reach this far below the base (no gap on slopes)", ge=0.0, le=5.0)


@dataclass(frozen=True, slots=True)
class SpeciesConfig:
    share: float = _f(0.0, "share of the stand's stems", ge=0.0)
    dbh_mean_m: float = _f(0.0, "mean DBH of this species (0: stems.dbh.mean_m)", ge=0.0,
                           le=3.0)
    dbh_sd_m: float = _f(0.0, "DBH standard deviation of this species (0: stems.dbh.sd_m)",
                         ge=0.0, le=1.0)


@dataclass(frozen=True, slots=True)
class DefectsConfig:
    """Defects drawn on natural stems. The shares say which defect makes an X stem X; the
    ranges are assumptions (no published rates or sizes were found: see the README)."""

    x_sweep: float = _f(0.15, "share of X stems made X by a sweep beyond "
                        "stems.other_threshold_m", ge=0.0)
    x_crook: float = _f(0.40, "share of X stems made X by a crook", ge=0.0)
    x_fork: float = _f(0.20, "share of X stems made X by a fork (a second leader)", ge=0.0)
    x_broken_top: float = _f(0.15, "share of X stems made X by a broken top", ge=0.0)
    x_double_stem: float = _f(0.10, "share of X stems made X by a double stem", ge=0.0)
    crook_offset_m: tuple[float, float] = _f(
        (0.04, 0.12), "crook: sideways shift of the stem above it", gt=0.0, le=2.0)
    crook_length_m: tuple[float, float] = _f(
        (0.3, 0.9), "crook: length of stem over which it bends (under 1 m)", gt=0.0, le=1.0)
    crook_height: tuple[float, float] = _f(
        (0.15, 0.6), "crook: where, as a fraction of the stem's height", gt=0.0,
        le=0.95)
    fork_height: tuple[float, float] = _f(
        (0.4, 0.8), "fork: where the second leader leaves, fraction of height", gt=0.0,
        le=0.95)
    fork_angle_deg: tuple[float, float] = _f(
        (15.0, 35.0), "fork: angle of the second leader from the stem", ge=1.0, le=80.0)
    fork_diameter_ratio: tuple[float, float] = _f(
        (0.5, 0.8), "fork: the second leader's diameter over the stem's there", gt=0.0,
        le=1.0)
    broken_height: tuple[float, float] = _f(
        (0.55, 0.85), "broken top: height left standing, fraction of the intact height",
        gt=0.2, le=0.98)
    double_height_m: tuple[float, float] = _f(
        (0.2, 1.0), "double stem: height at which the two stems part", ge=0.0, le=1.2)
    double_angle_deg: tuple[float, float] = _f(
        (5.0, 15.0), "double stem: angle of the second stem from the first", ge=1.0, le=45.0)
    double_diameter_ratio: tuple[float, float] = _f(
        (0.6, 0.9), "double stem: the second stem's diameter over the first's where they "
        "part", gt=0.0, le=1.0)
    lean_record_deg: float = _f(
        3.0, "a lean at least this large is listed among the stem's defects", ge=0.0,
        le=30.0)
    log_length_m: float = _f(
        4.6, "log length over which sweep is also given in cm/m, as graders measure it",
        gt=0.5, le=20.0)


@dataclass(frozen=True, slots=True)
class StandConfig:
    """Natural stands: species, taper, height from DBH, suppressed stems and defects as
    shapes. ``kind = "paper"`` keeps the paper's poles (stems.taper_exponent, heights drawn
    uniformly in stems.height_m, classes from sweep alone)."""

    kind: Literal["paper", "natural"] = _f(
        "paper", "paper: the paper's tapered poles; natural: species taper curves, height "
        "from DBH, suppressed stems and defects")
    site: Literal["mt", "vt", "ct", "clt"] = _f(
        "vt", "forest site type for the height model (Finnish: mt mesic or richer, vt "
        "sub-xeric, ct xeric, clt barren)")
    height_sd_scale: float = _f(
        1.0, "height residual spread as a share of the published one (0: heights on the "
        "curve)", ge=0.0, le=3.0)
    pine: SpeciesConfig = field(default_factory=lambda: SpeciesConfig(share=1.0),
                                metadata={"doc": "Scots pine: share and DBH"})
    spruce: SpeciesConfig = field(default_factory=SpeciesConfig,
                                  metadata={"doc": "Norway spruce: share and DBH"})
    birch: SpeciesConfig = field(default_factory=SpeciesConfig,
                                 metadata={"doc": "silver birch: share and DBH"})
    suppressed_share: float = _f(
        0.0, "share of stems that are suppressed (small DBH under the canopy)", ge=0.0,
        le=1.0)
    suppressed_dbh_m: tuple[float, float] = _f(
        (0.04, 0.10), "DBH range of suppressed stems (uniform)", gt=0.0, le=0.5)
    defects: DefectsConfig = field(default_factory=DefectsConfig,
                                   metadata={"doc": "defects of natural stems"})
    branches: bool = _f(True, "living branches in whorls in the crown, dead ones below it")
    foliage: bool = _f(True, "foliage in the crowns (and in saplings and shrubs): a "
                       "porous volume that stops a beam as Beer-Lambert says")
    foliage_as: Literal["auto", "volume", "facets"] = _f(
        "auto", "foliage cast as a turbid medium (a free path drawn per ray through each "
        "crown; Embree cast from compiled kernels), as facets (triangles; any backend), or "
        "auto: volume where the backend casts it")
    foliage_facet_m: float = _f(
        0.10, "foliage as facets: side of a facet (a shoot's size); its count follows from "
              "the crown's extinction", ge=0.02, le=0.5)
    saplings_per_ha: float = _f(0.0, "understory trees (a stem and a crown)", ge=0.0,
                                le=100_000.0)
    sapling_height_m: tuple[float, float] = _f(
        (0.5, 4.0), "sapling height range (uniform): below and above a SIC's 2.5 m",
        gt=0.1, le=10.0)
    shrubs_per_ha: float = _f(0.0, "shrubs: foliage near the ground", ge=0.0, le=100_000.0)
    shrub_height_m: tuple[float, float] = _f((0.3, 1.5), "shrub height range", gt=0.05,
                                             le=5.0)
    understory_sigma_per_m: float = _f(
        0.8, "extinction coefficient of sapling and shrub foliage (assumption)", gt=0.0,
        le=20.0)
    dead_wood_m3_per_ha: float = _f(
        0.0, "lying dead wood volume (Finnish NFI: 3.2 south, 7.6 north, 4.7 in forests "
             "in wood production)", ge=0.0, le=500.0)
    dead_wood_diameter_m: tuple[float, float] = _f(
        (0.10, 0.30), "lying log diameter range (NFI counts from 10 cm)", gt=0.01, le=2.0)
    dead_wood_length_m: tuple[float, float] = _f((2.0, 8.0), "lying log length range",
                                                 gt=0.1, le=40.0)
    stumps_per_ha: float = _f(0.0, "stumps of earlier fellings", ge=0.0, le=10_000.0)
    stump_height_m: tuple[float, float] = _f((0.10, 0.30), "stump height above ground",
                                             gt=0.0, le=2.0)
    detail_range_m: float = _f(
        0.0, "branches, foliage and ground objects are built only within this horizontal "
             "distance of the track (0: everywhere); stems always", ge=0.0, le=100_000.0)
    boulders_per_ha: float = _f(0.0, "boulders on the ground", ge=0.0, le=10_000.0)
    boulder_radius_m: tuple[float, float] = _f(
        (0.2, 0.8), "boulder horizontal semi-axis range (height 0.6 of it, 30 % sunk)",
        gt=0.01, le=5.0)


@dataclass(frozen=True, slots=True)
class DistributionConfig:
    kind: Literal["even", "uneven", "clustered"] = _f(
        "even", "even: grid with jitter; uneven: random with minimum spacing; "
        "clustered: Matérn cluster process with minimum spacing")
    jitter_m: float = _f(0.3, "even: uniform jitter around grid points", ge=0.0)
    min_spacing_m: float = _f(
        1.0, "uneven, clustered: minimum distance between stem bases", ge=0.0)
    clusters: int = _f(0, "clustered: number of clusters (0: one per 40 stems)", ge=0)
    cluster_radius_m: float = _f(8.0, "clustered: cluster radius", gt=0.0)
    edge_margin_m: float = _f(0.5, "stems stay this far inside the plot edge", ge=0.0)
    corridor_half_width_m: float = _f(
        2.0, "no stems within this distance of the sensor track (the strip road)", ge=0.0)
    strip_roads: int = _f(
        1, "strip roads cut free of stems: the track's and more, each track.pass_offset_m "
        "further to the left (so a multi-pass track drives on roads)", ge=1, le=20)


@dataclass(frozen=True, slots=True)
class TrackConfig:
    start_m: tuple[float, float, float] = _f(
        (0.0, -50.0, 2.0), "sensor start (x, y, height of the lidar above the ground)")
    end_m: tuple[float, float, float] = _f(
        (0.0, 50.0, 2.0), "sensor end (x, y, z: three numbers; z is not used, the height "
        "above the ground is start_m's)")
    speed_m_s: float = _f(1.0, "driving speed", gt=0.0, le=30.0)
    waypoints_m: tuple[tuple[float, float], ...] = _f(
        (), "points (x, y) driven through between start and end, corners rounded by "
        "turn_radius_m")
    turn_radius_m: float = _f(
        6.0, "radius of the arcs that round every corner (shrunk where legs are short)",
        gt=0.0, le=1000.0)
    passes: int = _f(
        1, "passes along the strip road, alternating direction (multi-pass scanning)",
        ge=1, le=20)
    pass_offset_m: float = _f(
        0.0, "lateral shift of each further pass (to the left of start->end); 0: the same "
        "road driven back in reverse gear, >0: U-turns between passes", ge=0.0, le=1000.0)
    accel_m_s2: float = _f(
        0.0, "acceleration and braking at the start and end of each leg; 0: the paper's "
        "constant speed from the first instant", ge=0.0, le=10.0)
    stop_s: float = _f(1.0, "standstill before reversing between passes", ge=0.0, le=600.0)
    follow_terrain: bool = _f(
        True, "pitch and roll follow the ground under the machine's footprint (false: level)")
    footprint_m: tuple[float, float] = _f(
        (4.0, 2.6), "machine length and width over which pitch and roll are taken", gt=0.0,
        le=50.0)
    mount_xy_m: tuple[float, float] = _f(
        (0.0, 0.0), "lidar position on the machine (x forward, y left of the base point; "
        "it places Ouster's sensor frame, not its lidar frame)")
    mount_rpy_deg: tuple[float, float, float] = _f(
        (0.0, 0.0, 0.0), "lidar roll, pitch, yaw on the machine (REP-103, degrees; of "
        "Ouster's sensor frame)")


@dataclass(frozen=True, slots=True)
class PoseErrorConfig:
    position_sd_m: float = _f(0.0, "white noise on x, y and z (GNSS), per sample", ge=0.0,
                              le=100.0)
    heading_sd_deg: float = _f(0.0, "white noise on heading (INS), per sample", ge=0.0,
                               le=180.0)
    bias_m: tuple[float, float, float] = _f((0.0, 0.0, 0.0), "constant position offset")
    drift_m_per_s: float = _f(
        0.0, "horizontal drift speed of the position error (direction drawn per seed)",
        ge=0.0, le=10.0)


@dataclass(frozen=True, slots=True)
class HarvesterConfig:
    node_id: int = _f(10, "CANopen node id of the harvester", ge=1, le=127)
    rate_hz: float = _f(100.0, "pose rate: SYNC period of the node's own SYNC producer",
                        gt=0.0, le=1000.0)
    heartbeat_ms: int = _f(100, "heartbeat producer time (0: off)", ge=0, le=65535)
    pose_error: PoseErrorConfig = field(
        default_factory=PoseErrorConfig,
        metadata={"doc": "GNSS/INS error applied to the pose on the bus (the truth is kept)"})


@dataclass(frozen=True, slots=True)
class SamplingConfig:
    points_per_stem: int = _f(1000, "surface points per stem (paper: 1000)", ge=0, le=10_000_000)
    terrain_density_per_m2: float = _f(
        10.0, "terrain points per square metre of plot", ge=0.0, le=10_000.0)


@dataclass(frozen=True, slots=True)
class UdpFaultConfig:
    loss: float = _f(0.0, "probability that a datagram is lost", ge=0.0, le=1.0)
    burst_rate: float = _f(
        0.0, "probability per datagram that a loss burst starts", ge=0.0, le=1.0)
    burst_packets: float = _f(10.0, "mean length of a loss burst, datagrams", ge=1.0,
                              le=1e6)
    duplicate: float = _f(0.0, "probability that a datagram arrives twice", ge=0.0, le=1.0)
    reorder: float = _f(
        0.0, "probability that a datagram swaps places with the next", ge=0.0, le=1.0)
    jitter_us: float = _f(
        0.0, "each datagram leaves up to this much later (uniform); a delayed one may be "
        "overtaken", ge=0.0, le=1e6)
    ports: Literal["both", "lidar", "imu"] = _f("both", "which datagrams the faults strike")


@dataclass(frozen=True, slots=True)
class LidarFaultConfig:
    dropout: float = _f(
        0.0, "probability that a whole frame is missing (its frame_id is skipped)", ge=0.0,
        le=1.0)
    dropout_at_s: tuple[float, ...] = _f(
        (), "track seconds at which frames go missing (the frame under way then)", ge=0.0)
    dropout_frames: int = _f(1, "frames missing at each dropout_at_s", ge=1, le=100_000)
    reinit_at_s: tuple[float, ...] = _f(
        (), "track seconds at which the sensor re-initialises: silent for reinit_gap_s, "
        "then a new init_id and frame_id from 0 (the HTTP API and metadata file change too)",
        ge=0.0)
    reinit_gap_s: float = _f(1.0, "how long a re-initialisation sends nothing", ge=0.0,
                             le=60.0)


@dataclass(frozen=True, slots=True)
class CanFaultConfig:
    loss: float = _f(
        0.0, "probability that a frame the harvester node sends (SYNC, PDO, heartbeat, "
        "TIME) is lost", ge=0.0, le=1.0)
    pose_delay_ms: float = _f(
        0.0, "pose TPDOs leave this long after their SYNC", ge=0.0, le=10_000.0)
    bus_off_at_s: tuple[float, ...] = _f(
        (), "track seconds at which the node goes bus-off (silent), recovering after "
        "bus_off_s with EMCY 0x8140", ge=0.0)
    bus_off_s: float = _f(1.0, "bus-off recovery time", gt=0.0, le=600.0)
    nmt_reset_at_s: tuple[float, ...] = _f(
        (), "track seconds at which a second master sends NMT 'reset node' to the harvester "
        "(it boots into PRE-OPERATIONAL)", ge=0.0)
    nmt_restart_s: float = _f(
        0.5, "that master sends NMT 'start' this long after each reset (0: never; the SIC "
        "must)", ge=0.0, le=600.0)


@dataclass(frozen=True, slots=True)
class FaultsConfig:
    seed: int = _f(0, "seed of the fault draws (0: from the run's seed)", ge=0,
                   le=2**63 - 1)
    udp: UdpFaultConfig = field(default_factory=UdpFaultConfig,
                                metadata={"doc": "lidar and IMU datagrams on the way"})
    lidar: LidarFaultConfig = field(default_factory=LidarFaultConfig,
                                    metadata={"doc": "the sensor's own faults"})
    can: CanFaultConfig = field(default_factory=CanFaultConfig,
                                metadata={"doc": "the harvester node's frames"})


@dataclass(frozen=True, slots=True)
class Scenario:
    name: str = _f("custom", "scenario name")
    description: str = _f("", "free text")
    seed: int = _f(0, "default random seed (--seed overrides)", ge=0, le=2**63 - 1)
    timestamp: str = _f(
        "20250213_035113", "timestamp written into ground truth (fixed: outputs are "
        "byte-identical per scenario and seed)")
    plot: PlotConfig = field(default_factory=PlotConfig, metadata={"doc": "plot"})
    terrain: TerrainConfig = field(default_factory=TerrainConfig, metadata={"doc": "terrain"})
    stems: StemsConfig = field(default_factory=StemsConfig, metadata={"doc": "stems"})
    distribution: DistributionConfig = field(default_factory=DistributionConfig,
                                             metadata={"doc": "stem placement"})
    stand: StandConfig = field(default_factory=StandConfig,
                               metadata={"doc": "natural stands (species, taper, height "
                                         "from DBH, defects); kind = 'paper' by default"})
    track: TrackConfig = field(default_factory=TrackConfig, metadata={"doc": "sensor track"})
    harvester: HarvesterConfig = field(default_factory=HarvesterConfig,
                                       metadata={"doc": "the harvester's CANopen node"})
    sampling: SamplingConfig = field(default_factory=SamplingConfig,
                                     metadata={"doc": "surface sampling (no lidar)"})
    faults: FaultsConfig = field(default_factory=FaultsConfig,
                                 metadata={"doc": "faults injected on purpose in live runs "
                                           "(none by default)"})
    sensor: SensorModel = field(default_factory=lambda: SENSOR_PRESETS[DEFAULT_SENSOR],
                                metadata={"doc": "the lidar's physics: preset = "
                                          "'os0-64-rev7' (the default), 'os0-64-rev6' or "
                                          "'ideal' (exact pencil rays, no noise); any key "
                                          "below overrides the preset"})
