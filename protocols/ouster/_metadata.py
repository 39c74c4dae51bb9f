"""Sensor metadata (the JSON a real sensor serves at /api/v1/sensor/metadata): build, write,
read and validate; and the SDK's ray model (shared/research/ouster-wire.md §3, §8)."""

from __future__ import annotations

import json
import math
import numbers
from dataclasses import dataclass, field, replace
from importlib import resources
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocols.ouster._errors import MetadataError
from protocols.ouster._packets import PacketFormat
from protocols.ouster._profiles import PROFILES
from protocols.text import short_repr

__all__ = ["MODES", "OS0_64_MODES", "SensorMetadata", "beam_rays", "os0_64_metadata",
           "xyz_from_range"]

MODES: tuple[str, ...] = ("512x10", "1024x10", "2048x10", "512x20", "1024x20", "4096x5")
# the modes tcf-hil's OS0-64 emulation offers (4096x5 metadata, which other Ouster sensors
# write, is read but not emulated)
OS0_64_MODES: tuple[str, ...] = MODES[:5]
SECTIONS: tuple[str, ...] = ("sensor_info", "config_params", "lidar_data_format",
                             "beam_intrinsics", "lidar_intrinsics", "imu_intrinsics",
                             "calibration_status")


def parse_mode(mode: str) -> tuple[int, int]:
    """``"1024x10"`` -> (1024 columns, 10 Hz)."""
    if not isinstance(mode, str):
        raise MetadataError(f"lidar_mode {_short(mode)}; expected a string, one of "
                            f"{', '.join(MODES)}")
    try:
        w, f = (int(v) for v in mode.split("x"))
    except ValueError as err:
        raise MetadataError(f"lidar_mode {mode!r}; expected COLUMNSxHZ, one of "
                            f"{', '.join(MODES)}") from err
    if mode not in MODES:
        raise MetadataError(f"lidar_mode {mode!r}; expected one of {', '.join(MODES)}")
    return w, f


def _short(v: Any) -> str:
    return short_repr(v, 60)


def _is_int(v: Any) -> bool:
    return isinstance(v, numbers.Integral) and not isinstance(v, bool)


def _is_number(v: Any) -> bool:
    """A finite real number (an int beyond the float range is not)."""
    if not isinstance(v, numbers.Real) or isinstance(v, bool):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _mat(v: Any, name: str) -> NDArray[np.float64]:
    flat = v
    if isinstance(v, list | tuple) and len(v) == 4 and all(isinstance(r, list | tuple)
                                                           for r in v):
        flat = [x for r in v for x in r]
    if not isinstance(flat, list | tuple) or len(flat) != 16 or \
            not all(_is_number(x) for x in flat):
        raise MetadataError(f"{name} = {_short(v)}; expected 16 finite numbers (a 4x4 matrix)")
    return np.asarray(flat, dtype=np.float64).reshape(4, 4)


@dataclass(frozen=True)
class SensorMetadata:
    """What tcf-hil needs of a sensor's metadata (all angles in degrees, lengths in mm)."""

    mode: str = "1024x10"
    profile: str = "RNG19_RFL8_SIG16_NIR16"
    columns_per_packet: int = 16
    prod_line: str = "OS-0-64"
    prod_sn: int = 992100000123
    init_id: int = 0x0ABCDE
    prod_pn: str = "840-105000-07"
    build_rev: str = "v3.1.0"
    image_rev: str = "ousteros-image-prod-bootes-v3.1.0"
    udp_dest: str = "127.0.0.1"
    udp_port_lidar: int = 7502
    udp_port_imu: int = 7503
    beam_altitude_deg: tuple[float, ...] = ()
    beam_azimuth_deg: tuple[float, ...] = ()
    pixel_shift_by_row: tuple[int, ...] = ()
    lidar_origin_to_beam_origin_mm: float = 27.116
    lidar_to_sensor: tuple[float, ...] = (-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 38.195, 0, 0, 0, 1)
    imu_to_sensor: tuple[float, ...] = (1, 0, 0, -2.441, 0, 1, 0, -9.725, 0, 0, 1, 7.533,
                                        0, 0, 0, 1)
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        parse_mode(self.mode)
        # Types first: a config POST or a hand-built document may hold anything.
        texts: tuple[tuple[str, object], ...] = (
            ("udp_profile_lidar", self.profile), ("udp_dest", self.udp_dest),
            ("prod_line", self.prod_line), ("prod_pn", self.prod_pn),
            ("build_rev", self.build_rev), ("image_rev", self.image_rev))
        for name, text in texts:
            if not isinstance(text, str):
                raise MetadataError(f"{name} {_short(text)}; expected a string")
        ints: tuple[tuple[str, object], ...] = (
            ("columns_per_packet", self.columns_per_packet),
            ("initialization_id", self.init_id), ("prod_sn", self.prod_sn),
            ("udp_port_lidar", self.udp_port_lidar), ("udp_port_imu", self.udp_port_imu))
        for name, num in ints:
            if not _is_int(num):
                raise MetadataError(f"{name} {_short(num)}; expected an integer")
        for name, port in (("udp_port_lidar", self.udp_port_lidar),
                           ("udp_port_imu", self.udp_port_imu)):
            if not 0 <= port <= 0xFFFF:
                raise MetadataError(f"{name} {port}; expected 0 .. 65535")
        for name, seq, check, what in (
                ("beam_altitude_angles", self.beam_altitude_deg, _is_number, "a finite number"),
                ("beam_azimuth_angles", self.beam_azimuth_deg, _is_number, "a finite number"),
                ("pixel_shift_by_row", self.pixel_shift_by_row, _is_int, "an integer")):
            if not isinstance(seq, tuple):
                raise MetadataError(f"{name} {_short(seq)}; expected a tuple")
            for i, x in enumerate(seq):
                if not check(x):
                    raise MetadataError(f"{name}[{i}] = {_short(x)}; expected {what}")
        if not _is_number(self.lidar_origin_to_beam_origin_mm):
            raise MetadataError(f"lidar_origin_to_beam_origin_mm "
                                f"{_short(self.lidar_origin_to_beam_origin_mm)}; expected a "
                                "finite number")
        # a float, as the loader makes it (an int of 10**30 would not survive the round trip:
        # found by hypothesis 6.170)
        object.__setattr__(self, "lidar_origin_to_beam_origin_mm",
                           float(self.lidar_origin_to_beam_origin_mm))
        for name, m in (("lidar_to_sensor_transform", self.lidar_to_sensor),
                        ("imu_to_sensor_transform", self.imu_to_sensor)):
            if not isinstance(m, tuple) or len(m) != 16:
                raise MetadataError(f"{name} {_short(m)}; expected a tuple of 16 numbers")
            _mat(m, name)
        if self.profile not in PROFILES:
            raise MetadataError(f"udp_profile_lidar {self.profile!r}; expected one of "
                                f"{', '.join(PROFILES)}")
        n = len(self.beam_altitude_deg)
        if n == 0 or len(self.beam_azimuth_deg) != n or len(self.pixel_shift_by_row) != n:
            raise MetadataError(
                f"beam_intrinsics: {n} altitudes, {len(self.beam_azimuth_deg)} azimuths and "
                f"{len(self.pixel_shift_by_row)} pixel shifts; expected equal non-zero counts")
        if self.columns_per_packet not in (8, 16, 32, 64, 128) or \
                self.columns % self.columns_per_packet:
            raise MetadataError(f"columns_per_packet {self.columns_per_packet}; expected a "
                                f"power of two from 8 that divides {self.columns}")
        for name, v, bits in (("initialization_id", self.init_id, 24),
                              ("prod_sn", self.prod_sn, 40)):
            if not 0 <= v < 1 << bits:
                raise MetadataError(f"{name} {v}; expected 0 .. {(1 << bits) - 1}")
        if not self.udp_dest or not self.udp_port_lidar:
            raise MetadataError("udp_dest and udp_port_lidar must be set (ouster-sdk turns the "
                                "profile OFF without them)")

    @property
    def columns(self) -> int:
        return parse_mode(self.mode)[0]

    @property
    def frequency_hz(self) -> int:
        return parse_mode(self.mode)[1]

    @property
    def pixels(self) -> int:
        return len(self.beam_altitude_deg)

    @property
    def packet_format(self) -> PacketFormat:
        return PacketFormat(PROFILES[self.profile], self.pixels, self.columns_per_packet,
                            self.columns)

    def with_changes(self, **kw: Any) -> SensorMetadata:
        """A copy with fields changed; pixel shifts rescale when the column count changes."""
        new_mode = kw.get("mode", self.mode)
        if new_mode != self.mode and "pixel_shift_by_row" not in kw:
            scale = parse_mode(new_mode)[0] / self.columns
            kw["pixel_shift_by_row"] = tuple(round(s * scale)
                                             for s in self.pixel_shift_by_row)
        return replace(self, **kw)

    def to_json(self) -> dict[str, Any]:
        """All seven sections, as ouster-sdk 1.0.1 validates them without issues."""
        w = self.columns
        cfg = {
            "lidar_mode": self.mode, "udp_dest": self.udp_dest,
            "udp_port_lidar": self.udp_port_lidar, "udp_port_imu": self.udp_port_imu,
            "udp_profile_lidar": self.profile, "udp_profile_imu": "LEGACY",
            "columns_per_packet": self.columns_per_packet, "operating_mode": "NORMAL",
            "azimuth_window": [0, 360000], "timestamp_mode": "TIME_FROM_INTERNAL_OSC",
            "signal_multiplier": 1, "phase_lock_enable": False, "phase_lock_offset": 0,
            "multipurpose_io_mode": "OFF", "nmea_baud_rate": "BAUD_9600",
            "nmea_ignore_valid_char": 0, "nmea_in_polarity": "ACTIVE_HIGH",
            "nmea_leap_seconds": 0, "sync_pulse_in_polarity": "ACTIVE_HIGH",
            "sync_pulse_out_angle": 360, "sync_pulse_out_frequency": 1,
            "sync_pulse_out_polarity": "ACTIVE_HIGH", "sync_pulse_out_pulse_width": 10,
        }
        b2l = [1, 0, 0, self.lidar_origin_to_beam_origin_mm, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1]
        return {
            "sensor_info": {
                "prod_line": self.prod_line, "prod_pn": self.prod_pn,
                "prod_sn": str(self.prod_sn), "initialization_id": self.init_id,
                "build_rev": self.build_rev, "image_rev": self.image_rev,
                "build_date": "2023-10-18T20:30:36Z", "status": "RUNNING",
            },
            "config_params": cfg,
            "lidar_data_format": {
                "columns_per_frame": w, "columns_per_packet": self.columns_per_packet,
                "pixels_per_column": self.pixels, "column_window": [0, w - 1],
                "pixel_shift_by_row": list(self.pixel_shift_by_row),
                "udp_profile_lidar": self.profile, "udp_profile_imu": "LEGACY",
            },
            "beam_intrinsics": {
                "beam_altitude_angles": list(self.beam_altitude_deg),
                "beam_azimuth_angles": list(self.beam_azimuth_deg),
                "beam_to_lidar_transform": b2l,
                "lidar_origin_to_beam_origin_mm": self.lidar_origin_to_beam_origin_mm,
            },
            "lidar_intrinsics": {"lidar_to_sensor_transform": list(self.lidar_to_sensor)},
            "imu_intrinsics": {"imu_to_sensor_transform": list(self.imu_to_sensor)},
            "calibration_status": {"reflectivity": {"valid": True,
                                                    "timestamp": "2023-10-18T20:30:36"}},
        }

    def dumps(self) -> str:
        return json.dumps(self.to_json(), indent=1) + "\n"

    @classmethod
    def from_json(cls, doc: Any) -> SensorMetadata:
        """Read the nested (7-section) metadata format; MetadataError names the field."""
        if not isinstance(doc, dict):
            raise MetadataError(f"metadata is a {type(doc).__name__}; expected a JSON object")
        missing = [s for s in SECTIONS if s not in doc]
        if missing:
            raise MetadataError(f"metadata lacks section(s) {', '.join(missing)}; all seven "
                                f"are needed: {', '.join(SECTIONS)}")

        def get(section: str, key: str, kind: type | tuple[type, ...]) -> Any:
            sec = doc[section]
            if not isinstance(sec, dict) or key not in sec:
                raise MetadataError(f"{section}.{key} is missing")
            v = sec[key]
            if not isinstance(v, kind) or (isinstance(v, bool) and kind is not bool):
                raise MetadataError(f"{section}.{key} = {v!r}; expected {kind}")
            return v

        ldf = "lidar_data_format"
        w = get(ldf, "columns_per_frame", int)
        if w not in {parse_mode(m)[0] for m in MODES}:
            raise MetadataError(f"{ldf}.columns_per_frame = {_short(w)}; expected the columns "
                                f"of a lidar_mode ({', '.join(MODES)})")
        for section in SECTIONS[:-1]:  # calibration_status is not read
            if not isinstance(doc[section], dict):
                raise MetadataError(f"{section} = {_short(doc[section])}; expected a JSON "
                                    "object")
        mode = doc["config_params"].get("lidar_mode")
        if not isinstance(mode, str) or parse_mode(mode)[0] != w:
            mode = f"{w}x10" if f"{w}x10" in MODES else f"{w}x5"
        alt = get("beam_intrinsics", "beam_altitude_angles", list)
        az = get("beam_intrinsics", "beam_azimuth_angles", list)
        shift = get(ldf, "pixel_shift_by_row", list)
        for name, arr in (("beam_altitude_angles", alt), ("beam_azimuth_angles", az),
                          ("pixel_shift_by_row", shift)):
            for i, v in enumerate(arr):
                if not _is_number(v):
                    raise MetadataError(f"{name}[{i}] = {_short(v)}; expected a finite number")
        si = doc["sensor_info"]
        cp = doc["config_params"]

        def integer(section: str, key: str, text_ok: bool = False) -> int:
            v = doc[section].get(key, 0)
            if text_ok and isinstance(v, str) and v.isascii() and v.isdecimal() and \
                    len(v) < 40:
                return int(v)
            if not _is_int(v):
                raise MetadataError(f"{section}.{key} = {_short(v)}; expected an integer"
                                    + (" or a decimal string" if text_ok else ""))
            return int(v)

        origin = doc["beam_intrinsics"].get("lidar_origin_to_beam_origin_mm", 0.0)
        if not _is_number(origin):
            raise MetadataError(f"beam_intrinsics.lidar_origin_to_beam_origin_mm = "
                                f"{_short(origin)}; expected a finite number")
        return cls(
            mode=mode, profile=get(ldf, "udp_profile_lidar", str),
            columns_per_packet=get(ldf, "columns_per_packet", int),
            prod_line=str(si.get("prod_line", "")),
            prod_sn=integer("sensor_info", "prod_sn", text_ok=True),
            init_id=integer("sensor_info", "initialization_id"),
            prod_pn=str(si.get("prod_pn", "")), build_rev=str(si.get("build_rev", "")),
            image_rev=str(si.get("image_rev", "")), udp_dest=str(cp.get("udp_dest", "")),
            udp_port_lidar=integer("config_params", "udp_port_lidar"),
            udp_port_imu=integer("config_params", "udp_port_imu"),
            beam_altitude_deg=tuple(float(v) for v in alt),
            beam_azimuth_deg=tuple(float(v) for v in az),
            pixel_shift_by_row=tuple(int(v) for v in shift),
            lidar_origin_to_beam_origin_mm=float(origin),
            lidar_to_sensor=tuple(_mat(get("lidar_intrinsics", "lidar_to_sensor_transform",
                                           list), "lidar_to_sensor_transform").ravel()),
            imu_to_sensor=tuple(_mat(get("imu_intrinsics", "imu_to_sensor_transform", list),
                                     "imu_to_sensor_transform").ravel()),
        )

    @classmethod
    def loads(cls, text: str) -> SensorMetadata:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as err:
            raise MetadataError(f"metadata is not JSON: {err.msg} (line {err.lineno}, column "
                                f"{err.colno})") from err
        except ValueError as err:  # an integer beyond the str-conversion digit limit
            raise MetadataError(f"metadata is not JSON tcf-hil reads: "
                                f"{str(err).splitlines()[0]}") from err
        except RecursionError as err:
            raise MetadataError("metadata is not JSON tcf-hil reads: nested too deeply") from err
        return cls.from_json(doc)


def os0_64_metadata(mode: str = "1024x10", profile: str = "RNG19_RFL8_SIG16_NIR16",
                    **kw: Any) -> SensorMetadata:
    """The shipped OS0-64 calibration (derived: every other beam of a real OS-0-128)."""
    cal = json.loads((resources.files(__package__) / "os0_64_calibration.json")
                     .read_text("utf-8"))
    w = parse_mode(mode)[0]
    shift = tuple(round(s * w / 1024) for s in cal["pixel_shift_by_row_1024"])
    return SensorMetadata(
        mode=mode, profile=profile, prod_line=cal["prod_line"], prod_pn=cal["prod_pn"],
        build_rev=cal["build_rev"], image_rev=cal["image_rev"],
        beam_altitude_deg=tuple(cal["beam_altitude_angles"]),
        beam_azimuth_deg=tuple(cal["beam_azimuth_angles"]), pixel_shift_by_row=shift,
        lidar_origin_to_beam_origin_mm=cal["lidar_origin_to_beam_origin_mm"],
        lidar_to_sensor=tuple(cal["lidar_to_sensor_transform"]),
        imu_to_sensor=tuple(cal["imu_to_sensor_transform"]), **kw)


def beam_rays(meta: SensorMetadata) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The SDK's ray model in the *sensor* frame for the staggered (H, W) image.

    Returns:
        (origins (H, W, 3) in metres, unit directions (H, W, 3)). A return with encoded
        RANGE r (mm) lies at origin + (r / 1000 - n) * direction with n the beam-origin
        offset in metres, i.e. the ray starts at the beam origin and the encoded range
        counts from the lidar axis.
    """
    H, W = meta.pixels, meta.columns
    n = meta.lidar_origin_to_beam_origin_mm
    theta_e = 2.0 * np.pi * (1.0 - np.arange(W) / W)[None, :]
    theta_a = -np.radians(np.asarray(meta.beam_azimuth_deg))[:, None]
    phi = np.radians(np.asarray(meta.beam_altitude_deg))[:, None]
    d = np.stack(np.broadcast_arrays(np.cos(theta_e + theta_a) * np.cos(phi),
                                     np.sin(theta_e + theta_a) * np.cos(phi),
                                     np.sin(phi)), axis=-1)
    b = np.stack(np.broadcast_arrays(n * np.cos(theta_e), n * np.sin(theta_e),
                                     np.zeros_like(theta_e)), axis=-1) * np.ones((H, 1, 1))
    m = np.asarray(meta.lidar_to_sensor, dtype=np.float64).reshape(4, 4)
    rot, tr = m[:3, :3], m[:3, 3]
    origins = (b @ rot.T + tr) / 1000.0
    dirs = d @ rot.T
    return origins, dirs


def xyz_from_range(meta: SensorMetadata, range_mm: NDArray[np.integer]) -> NDArray[np.float64]:
    """Points (H, W, 3) in metres, sensor frame, from a staggered RANGE image (0 = no return
    gives NaN)."""
    o, d = beam_rays(meta)
    r = np.asarray(range_mm, dtype=np.float64) / 1000.0
    n = meta.lidar_origin_to_beam_origin_mm / 1000.0
    p = o + (r - n)[..., None] * d
    p[r == 0] = np.nan
    return p
