"""Sensor metadata (the JSON a real sensor serves at /api/v1/sensor/metadata): build, write,
read and validate; and the SDK's ray model (shared/research/ouster-wire.md §3, §8)."""

from __future__ import annotations

import copy
import json
import math
import numbers
import re
from dataclasses import dataclass, field, replace
from importlib import resources
from typing import Any

import numpy as np
from numpy.typing import NDArray

from protocols.ouster._errors import MetadataError
from protocols.ouster._packets import PacketFormat
from protocols.ouster._profiles import PROFILES
from protocols.text import short_repr

__all__ = ["FIRMWARES", "MODES", "OS0_64_MODES", "Firmware", "SensorMetadata", "beam_rays",
           "firmware_of", "legacy_metadata", "os0_64_metadata", "xyz_from_range"]

MODES: tuple[str, ...] = ("512x10", "1024x10", "2048x10", "512x20", "1024x20", "4096x5")
# the modes tcf-hil's OS0-64 emulation offers (4096x5 metadata, which other Ouster sensors
# write, is read but not emulated)
OS0_64_MODES: tuple[str, ...] = MODES[:5]
#: the keys of each section that SensorMetadata models (what :meth:`SensorMetadata.to_json`
#: writes over a recorded document's)
MODELLED: dict[str, tuple[str, ...]] = {
    "sensor_info": ("prod_line", "prod_sn", "initialization_id", "prod_pn", "build_rev",
                    "image_rev"),
    "config_params": ("lidar_mode", "udp_dest", "udp_port_lidar", "udp_port_imu",
                      "udp_profile_lidar", "columns_per_packet"),
    "lidar_data_format": ("columns_per_frame", "columns_per_packet", "pixels_per_column",
                          "column_window", "pixel_shift_by_row", "udp_profile_lidar",
                          "header_type"),
    "beam_intrinsics": ("beam_altitude_angles", "beam_azimuth_angles",
                        "lidar_origin_to_beam_origin_mm"),
    "lidar_intrinsics": ("lidar_to_sensor_transform",),
    "imu_intrinsics": ("imu_to_sensor_transform",),
    "calibration_status": (),
}
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


# ouster-sdk 1.0.1's defaults where metadata leaves a key out (ouster_core/src/metadata.cpp,
# data_format.cpp, sensor_info.cpp)
DEFAULT_COLUMNS_PER_PACKET = 16
DEFAULT_IMU_TO_SENSOR = (1, 0, 0, 6.253, 0, 1, 0, -11.775, 0, 0, 1, 7.645, 0, 0, 0, 1)
DEFAULT_LIDAR_TO_SENSOR = (-1, 0, 0, 0, 0, -1, 0, 0, 0, 0, 1, 36.18, 0, 0, 0, 1)
_LEGACY_SECTIONS: dict[str, tuple[str, ...]] = {  # the flat keys each nested section takes
    "config_params": ("udp_port_imu", "udp_port_lidar", "lidar_mode"),
    "beam_intrinsics": ("lidar_origin_to_beam_origin_mm", "beam_altitude_angles",
                        "beam_azimuth_angles", "beam_to_lidar_transform"),
    "sensor_info": ("prod_line", "status", "prod_pn", "prod_sn", "initialization_id",
                    "build_rev", "build_date", "image_rev"),
}


def _kept(doc: dict[str, Any]) -> dict[str, Any]:
    """What :meth:`SensorMetadata.to_json` keeps of a document read: all of it, where it is
    plain JSON (no NaN or infinity, which a strict writer refuses); else nothing."""
    try:
        return {"document": json.loads(json.dumps(doc, allow_nan=False))}
    except (ValueError, TypeError, RecursionError):
        return {}


def legacy_metadata(doc: dict[str, Any]) -> dict[str, Any]:
    """A nested document in the legacy flat format, as ouster-sdk wrote it beside recordings
    of firmware 2.x (``tests/metadata/*_legacy.json``): the sensor_info, beam, lidar and
    IMU keys at the top, the data format under ``data_format``, and of the configuration
    the mode and the ports; the inverse of :func:`nested_metadata`."""
    flat: dict[str, Any] = {}
    for name in ("sensor_info", "beam_intrinsics", "lidar_intrinsics", "imu_intrinsics"):
        flat.update(copy.deepcopy(doc[name]))
    for key in _LEGACY_SECTIONS["config_params"]:
        if key in doc["config_params"]:
            flat[key] = doc["config_params"][key]
    flat["data_format"] = copy.deepcopy(doc["lidar_data_format"])
    return flat


def nested_metadata(doc: Any) -> dict[str, Any]:
    """``doc`` in the nested format: as it is where it has all seven sections; the legacy
    flat format (none of them) moved into them key by key as ouster-sdk does
    (``convert_legacy_to_nonlegacy``: ``data_format`` becomes ``lidar_data_format``, the
    transforms their intrinsics, and so on); some sections but not all: MetadataError,
    as ouster-sdk refuses it."""
    if not isinstance(doc, dict):
        raise MetadataError(f"metadata is a {type(doc).__name__}; expected a JSON object")
    present = [s for s in SECTIONS if s in doc]
    if len(present) == len(SECTIONS):
        return doc
    if present:
        missing = [s for s in SECTIONS if s not in doc]
        raise MetadataError(f"metadata lacks section(s) {', '.join(missing)}; the nested "
                            f"format has all seven ({', '.join(SECTIONS)}), the legacy flat "
                            "one none")
    out: dict[str, Any] = {name: {} for name in SECTIONS}
    taken = set()
    for key, section in (("lidar_to_sensor_transform", "lidar_intrinsics"),
                         ("imu_to_sensor_transform", "imu_intrinsics")):
        if key in doc:
            out[section][key] = doc[key]
            taken.add(key)
    if "data_format" in doc:
        out["lidar_data_format"] = doc["data_format"]
        taken.add("data_format")
    for section, keys in _LEGACY_SECTIONS.items():
        for key in keys:
            if key in doc:
                out[section][key] = doc[key]
                taken.add(key)
    for key, value in doc.items():
        if key not in taken and key not in out:
            out[key] = value
    return out


def default_pixel_shifts(columns: int, pixels: int) -> list[int]:
    """ouster-sdk's pixel shifts where metadata has none (``default_data_format``: 16
    repeats of four staggers, for 64 beams; resized to ``pixels`` with zeros)."""
    step = {512: 3, 1024: 6, 2048: 12, 4096: 24}.get(columns, 0)
    shifts = [3 * step, 2 * step, step, 0] * 16
    return (shifts + [0] * pixels)[:pixels]


def beams_of_prod_line(prod_line: str) -> int | None:
    """The beam count a product line names (``OS-1-16-A0``: 16), or None."""
    parts = prod_line.split("-")
    if len(parts) >= 3 and parts[0] == "OS" and parts[2].isdecimal() and len(parts[2]) < 5:
        return int(parts[2])
    return None


def default_lidar_origin_to_beam_origin_mm(prod_line: str) -> float:
    """ouster-sdk's ``default_lidar_origin_to_beam_origin`` by product line."""
    for prefix, mm in (("OS-0-", 27.67), ("OS-1-", 15.806), ("OS-2-", 13.762)):
        if prod_line.startswith(prefix):
            return mm
    return 12.163  # the first generation's


_LDF = "lidar_data_format"


class _Sections:
    """A nested metadata document's sections (each a dict, {} where the document's is not
    one), read with ouster-sdk's defaults; every error names the field."""

    def __init__(self, sec: dict[str, dict[str, Any]]) -> None:
        self.sec = sec

    def get(self, section: str, key: str, kind: type | tuple[type, ...], default: Any = None
            ) -> Any:
        """``section.key`` of type ``kind``; ``default`` where it is missing (None: it is
        required)."""
        if key not in self.sec[section]:
            if default is not None:
                return default
            raise MetadataError(f"{section}.{key} is missing")
        v = self.sec[section][key]
        if not isinstance(v, kind) or (isinstance(v, bool) and kind is not bool):
            raise MetadataError(f"{section}.{key} = {_short(v)}; expected {kind}")
        return v

    def integer(self, section: str, key: str, default: int = 0, text_ok: bool = False
                ) -> int:
        """``section.key`` as an integer (``text_ok``: a decimal string too)."""
        v = self.sec[section].get(key, default)
        if text_ok and isinstance(v, str) and v.isascii() and v.isdecimal() and len(v) < 40:
            return int(v)
        if not _is_int(v):
            raise MetadataError(f"{section}.{key} = {_short(v)}; expected an integer"
                                + (" or a decimal string" if text_ok else ""))
        return int(v)


def _frame_shape(r: _Sections) -> tuple[int, str]:
    """The columns per frame and the lidar mode (the mode that has those columns where the
    document's does not)."""
    mode = r.sec["config_params"].get("lidar_mode")
    mode_w = parse_mode(mode)[0] if isinstance(mode, str) and mode in MODES else None
    if "columns_per_frame" not in r.sec[_LDF] and mode_w is None:
        raise MetadataError(f"{_LDF}.columns_per_frame is missing, and "
                            f"config_params.lidar_mode {_short(mode)} gives none")
    w = r.get(_LDF, "columns_per_frame", int, mode_w)
    if w not in {parse_mode(m)[0] for m in MODES}:
        raise MetadataError(f"{_LDF}.columns_per_frame = {_short(w)}; expected the "
                            f"columns of a lidar_mode ({', '.join(MODES)})")
    if not isinstance(mode, str) or mode not in MODES or parse_mode(mode)[0] != w:
        mode = f"{w}x10" if f"{w}x10" in MODES else f"{w}x5"
    return w, mode


@dataclass(frozen=True)
class _Beams:
    """The beams as a document gives them (:func:`_beams`)."""

    prod_line: str
    alt: list[Any]
    az: list[Any]
    shift: list[Any]
    origin: Any


def _beams(r: _Sections, w: int) -> _Beams:
    """The beams' angles (as many as the pixels per column: those the product line names,
    else 64), the pixel shifts (resized to the beams, as ouster-sdk does) and the beam
    origin's offset."""
    alt = r.get("beam_intrinsics", "beam_altitude_angles", list)
    az = r.get("beam_intrinsics", "beam_azimuth_angles", list)
    prod_line = str(r.sec["sensor_info"].get("prod_line", ""))
    # as ouster-sdk: the beams the product line names, else 64
    h = r.get(_LDF, "pixels_per_column", int, beams_of_prod_line(prod_line) or 64)
    for name, arr in (("beam_altitude_angles", alt), ("beam_azimuth_angles", az)):
        if len(arr) != h:
            raise MetadataError(f"beam_intrinsics.{name} has {len(arr)} angles; expected "
                                f"{h} (pixels_per_column)")
    shift = r.get(_LDF, "pixel_shift_by_row", list, default_pixel_shifts(w, h))
    for name, arr in (("beam_altitude_angles", alt), ("beam_azimuth_angles", az),
                      ("pixel_shift_by_row", shift)):
        for i, v in enumerate(arr):
            if not _is_number(v):
                raise MetadataError(f"{name}[{i}] = {_short(v)}; expected a finite number")
    shift = (list(shift) + [0] * h)[:h]  # as ouster-sdk resizes it to the beams
    origin = r.sec["beam_intrinsics"].get("lidar_origin_to_beam_origin_mm",
                                          default_lidar_origin_to_beam_origin_mm(prod_line))
    if not _is_number(origin):
        raise MetadataError(f"beam_intrinsics.lidar_origin_to_beam_origin_mm = "
                            f"{_short(origin)}; expected a finite number")
    return _Beams(prod_line, alt, az, shift, origin)


def _lidar_format(r: _Sections, w: int) -> tuple[str, str, list[Any]]:
    """The lidar profile, the header type and the column window."""
    profile = r.get(_LDF, "udp_profile_lidar", str, "LEGACY")
    header_type = r.sec[_LDF].get("header_type", "")
    if not isinstance(header_type, str):
        raise MetadataError(f"{_LDF}.header_type = {_short(header_type)}; expected "
                            "STANDARD or FUSA")
    window = r.get(_LDF, "column_window", list, [0, w - 1])
    if len(window) != 2 or not all(_is_int(c) and 0 <= c < w for c in window):
        raise MetadataError(f"{_LDF}.column_window = {_short(window)}; expected two "
                            f"columns in 0 .. {w - 1}")
    return profile, header_type, window


def _destination(r: _Sections) -> tuple[str, int, int]:
    """Where the sensor sent its data, as ouster-sdk reads it: "" and 0 where the document
    names none (a sensor saved before a destination was set, the legacy flat format, whose
    files leave the configuration out); firmware 1.12/1.13 called it udp_ip. Who sends or
    replays chooses then (a replay sends to 127.0.0.1 and finds the ports in the capture).
    Only a lidar profile that is OFF means no lidar data."""
    cp = r.sec["config_params"]
    udp_dest = cp.get("udp_dest", cp.get("udp_ip", ""))
    if not isinstance(udp_dest, str):
        raise MetadataError(f"config_params.udp_dest = {_short(udp_dest)}; expected an "
                            "address (a string)")
    port = r.integer("config_params", "udp_port_lidar", 0)
    imu_port = r.integer("config_params", "udp_port_imu", 0)
    for name, v in (("udp_port_lidar", port), ("udp_port_imu", imu_port)):
        if not 0 <= v <= 0xFFFF:
            raise MetadataError(f"config_params.{name} = {v}; expected 0 .. 65535 (0: "
                                "not set)")
    for section in ("config_params", _LDF):
        if r.sec[section].get("udp_profile_lidar") == "OFF":
            raise MetadataError(f"{section}.udp_profile_lidar is OFF: the sensor sends no "
                                "lidar data")
    return udp_dest, port, imu_port


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
    # the emulator's own destination and the sensor's default ports; read from a document
    # that names none, "" and 0 (as ouster-sdk reads it: "not set")
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
    header_type: str = ""  # lidar_data_format.header_type ("": the profile's, as the SDK)
    # lidar_data_format.column_window: the first and last columns sent (inclusive; it wraps
    # past the frame's end where first > last); None: all
    column_window: tuple[int, int] | None = None
    extra: dict[str, Any] = field(default_factory=dict, compare=False, repr=False)

    def __post_init__(self) -> None:
        parse_mode(self.mode)
        # Types first: a config POST or a hand-built document may hold anything.
        texts: tuple[tuple[str, object], ...] = (
            ("udp_profile_lidar", self.profile), ("udp_dest", self.udp_dest),
            ("prod_line", self.prod_line), ("prod_pn", self.prod_pn),
            ("build_rev", self.build_rev), ("image_rev", self.image_rev),
            ("header_type", self.header_type))
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
        cw = self.column_window
        if cw is not None and (not isinstance(cw, tuple) or len(cw) != 2 or not all(
                _is_int(c) and 0 <= c < self.columns for c in cw)):
            raise MetadataError(f"column_window {_short(cw)}; expected two columns in "
                                f"0 .. {self.columns - 1}")
        if self.header_type not in ("", "STANDARD", "FUSA"):
            raise MetadataError(f"header_type {self.header_type!r}; expected STANDARD or FUSA")
        n = len(self.beam_altitude_deg)
        if n == 0 or len(self.beam_azimuth_deg) != n or len(self.pixel_shift_by_row) != n:
            raise MetadataError(
                f"beam_intrinsics: {n} altitudes, {len(self.beam_azimuth_deg)} azimuths and "
                f"{len(self.pixel_shift_by_row)} pixel shifts; expected equal non-zero counts")
        cpp = self.columns_per_packet
        if cpp < 1 or self.columns % cpp:
            raise MetadataError(f"columns_per_packet {cpp}; expected a divisor of "
                                f"{self.columns} (columns per frame)")
        size = PROFILES[self.profile].packet_bytes(n, cpp)
        if size > 65535:  # (as ouster-sdk refuses it)
            raise MetadataError(f"columns_per_packet {cpp}: a {self.profile} packet of {n} "
                                f"pixels would be {size} bytes; a UDP datagram holds 65535")
        for name, v, bits in (("initialization_id", self.init_id, 24),
                              ("prod_sn", self.prod_sn, 40)):
            if not 0 <= v < 1 << bits:
                raise MetadataError(f"{name} {v}; expected 0 .. {(1 << bits) - 1}")

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
    def firmware(self) -> tuple[int, int, int] | None:
        """The firmware version in ``image_rev`` (else ``build_rev``), e.g. (3, 1, 0)."""
        for text in (self.image_rev, self.build_rev):
            m = re.search(r"v(\d+)\.(\d+)\.(\d+)", text)
            if m:
                return int(m[1]), int(m[2]), int(m[3])
        return None

    @property
    def packet_format(self) -> PacketFormat:
        """The lidar packets' layout, their footer as :data:`FIRMWARES` says the firmware
        ended it (a CRC-64/XZ from 2.5 on, or where the firmware is not named or not in the
        table): real packets of firmware 2.5.2 and 3.2.0 in
        ouster-sdk's test data carry one (``same_ports_nonlegacy.pcap``, ``crc_test.pcap``);
        those of 2.2 to 2.4 carry 0xdeadbeef0000c0de or zeros there (``duplicate_id.pcap``,
        ``OS-0-32-U1_v2.2.0``, ``OS-2-128-U1_v2.3.0``); the FUSA header has none
        (ouster-sdk reads none, and a firmware 3.1 FUSA packet's footer is zeros)."""
        fmt = PacketFormat.create(self.profile, self.pixels, self.columns_per_packet,
                                  self.columns, self.header_type or None)
        fw = firmware_of(self)
        if fmt.crc and fw is not None and fw.footer != "crc":
            fmt = replace(fmt, crc=False,
                          footer=FOOTER_PLACEHOLDER if fw.footer == "placeholder" else b"")
        return fmt

    def with_changes(self, **kw: Any) -> SensorMetadata:
        """A copy with fields changed; pixel shifts rescale when the column count changes."""
        new_mode = kw.get("mode", self.mode)
        if new_mode != self.mode and "pixel_shift_by_row" not in kw:
            scale = parse_mode(new_mode)[0] / self.columns
            kw["pixel_shift_by_row"] = tuple(round(s * scale)
                                             for s in self.pixel_shift_by_row)
        if new_mode != self.mode and "column_window" not in kw:
            kw["column_window"] = None  # (a sensor's new mode sends every column)
        return replace(self, **kw)

    def to_json(self) -> dict[str, Any]:
        """All seven sections, as ouster-sdk 1.0.1 validates them without issues. Metadata
        read from a document (:meth:`from_json`) writes that document in the nested format,
        every key it had kept, with the values modelled here (:data:`MODELLED`) put in.
        Firmware before 2.2 had no lidar profiles: no ``udp_profile_lidar`` (LEGACY)."""
        doc = self._own_json()
        fw = self.firmware
        if fw is not None and fw < (2, 2, 0) and self.profile == "LEGACY":
            for name in ("config_params", "lidar_data_format"):
                doc[name].pop("udp_profile_lidar", None)
                doc[name].pop("udp_profile_imu", None)
        recorded = self.extra.get("document")
        if not isinstance(recorded, dict):
            return doc
        out: dict[str, Any] = {}
        for name in SECTIONS:
            ours, theirs = doc[name], recorded.get(name)
            theirs = theirs if isinstance(theirs, dict) else {}
            out[name] = {**ours, **copy.deepcopy(theirs),
                         **{k: ours[k] for k in MODELLED[name] if k in ours}}
        for k, v in recorded.items():  # keys beside the sections, as they were
            out.setdefault(k, copy.deepcopy(v))
        return out

    def _own_json(self) -> dict[str, Any]:
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
                "pixels_per_column": self.pixels,
                "column_window": list(self.column_window or (0, w - 1)),
                "pixel_shift_by_row": list(self.pixel_shift_by_row),
                "udp_profile_lidar": self.profile, "udp_profile_imu": "LEGACY",
                **({"header_type": self.header_type} if self.header_type else {}),
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

    def dumps(self, legacy: bool | None = None) -> str:
        """The metadata file: nested (:meth:`to_json`), or the legacy flat format
        (:func:`legacy_metadata`) that ouster-sdk wrote beside recordings of firmware before
        3.0; ``legacy`` None: as the firmware named in ``image_rev`` had it."""
        fw = self.firmware
        if legacy is None:
            legacy = fw is not None and fw < (3, 0, 0)
        doc = legacy_metadata(self.to_json()) if legacy else self.to_json()
        return json.dumps(doc, indent=1) + "\n"

    @classmethod
    def from_json(cls, doc: Any) -> SensorMetadata:
        """Read sensor metadata as ouster-sdk 1.0.1 reads it: the nested format (firmware
        2.0 on: seven sections) or the legacy flat one (firmware 1.12 to 2.x, and what
        ouster-sdk wrote beside recordings), with ouster-sdk's defaults where a key is
        missing (:func:`nested_metadata`); MetadataError names the field. Read in the
        document's order: the frame's shape, the beams, the lidar data format, where the
        data went, the transforms."""
        doc = nested_metadata(doc)
        r = _Sections({name: (doc[name] if isinstance(doc[name], dict) else {})
                       for name in SECTIONS})
        w, mode = _frame_shape(r)
        beams = _beams(r, w)
        profile, header_type, window = _lidar_format(r, w)
        udp_dest, port, imu_port = _destination(r)
        transforms = [tuple(_mat(r.get(section, key, list, list(default)), key).ravel())
                      for section, key, default in (
                          ("lidar_intrinsics", "lidar_to_sensor_transform",
                           DEFAULT_LIDAR_TO_SENSOR),
                          ("imu_intrinsics", "imu_to_sensor_transform",
                           DEFAULT_IMU_TO_SENSOR))]
        si = r.sec["sensor_info"]
        return cls(
            mode=mode, profile=profile,
            columns_per_packet=r.get(_LDF, "columns_per_packet", int,
                                     DEFAULT_COLUMNS_PER_PACKET),
            prod_line=beams.prod_line,
            prod_sn=r.integer("sensor_info", "prod_sn", text_ok=True),
            init_id=r.integer("sensor_info", "initialization_id"),
            prod_pn=str(si.get("prod_pn", "")), build_rev=str(si.get("build_rev", "")),
            image_rev=str(si.get("image_rev", "")), udp_dest=udp_dest,
            udp_port_lidar=port,
            udp_port_imu=imu_port,
            beam_altitude_deg=tuple(float(v) for v in beams.alt),
            beam_azimuth_deg=tuple(float(v) for v in beams.az),
            pixel_shift_by_row=tuple(int(v) for v in beams.shift),
            lidar_origin_to_beam_origin_mm=float(beams.origin),
            lidar_to_sensor=transforms[0], imu_to_sensor=transforms[1],
            header_type=header_type,
            column_window=None if tuple(window) == (0, w - 1) else (int(window[0]),
                                                                     int(window[1])),
            extra=_kept(doc),
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


@dataclass(frozen=True)
class Firmware:
    """What a firmware version's sensor wrote, as far as ouster-sdk's test data shows it
    (metadata written by firmware 1.12 to 3.2 and captures of 2.0 to 3.2; Ouster's release
    notes were not at hand): the lidar profiles it had, how its packet footer ends, and the
    revision strings it reports."""

    version: str
    profiles: tuple[str, ...]
    footer: str  # "crc", "placeholder" (0xdeadbeef0000c0de) or "zeros"

    @property
    def image_rev(self) -> str:
        family = "aries" if self.version < "3" else "bootes"
        return f"ousteros-image-prod-{family}-v{self.version}.0"

    @property
    def build_rev(self) -> str:
        return f"v{self.version}.0"


_ALL = ("LEGACY", "RNG19_RFL8_SIG16_NIR16", "RNG19_RFL8_SIG16_NIR16_DUAL", "RNG15_RFL8_NIR8")
#: firmware tcf-hil emulates on request (``[sensor] firmware``). Profiles: the metadata of
#: 2.0 and 2.1 has no udp_profile_lidar (LEGACY only); 2.2 names it, and the three
#: non-legacy profiles appear in 2.2 to 2.4 recordings. Footers: zeros in a 2.2 capture
#: (OS-0-32-U1_v2.2.0), 0xdeadbeef0000c0de in 2.3 and 2.4 ones (OS-0-128-U1_v2.3.0,
#: duplicate_id 2.4.0), a CRC-64/XZ from 2.5 (same_ports_nonlegacy 2.5.2, crc_test 3.2.0).
FIRMWARES: dict[str, Firmware] = {f.version: f for f in (
    Firmware("2.0", ("LEGACY",), "zeros"),
    Firmware("2.1", ("LEGACY",), "zeros"),
    Firmware("2.2", _ALL, "zeros"),
    Firmware("2.3", _ALL, "placeholder"),
    Firmware("2.4", _ALL, "placeholder"),
    Firmware("2.5", _ALL, "crc"),
    Firmware("3.0", _ALL, "crc"),
    Firmware("3.1", _ALL, "crc"),
)}
FOOTER_PLACEHOLDER = bytes.fromhex("dec00000efbeadde")


def firmware_of(meta: SensorMetadata) -> Firmware | None:
    """The emulated firmware entry for the version ``meta`` names, if any."""
    fw = meta.firmware
    return None if fw is None else FIRMWARES.get(f"{fw[0]}.{fw[1]}")


def os0_64_metadata(mode: str = "1024x10", profile: str = "RNG19_RFL8_SIG16_NIR16",
                    firmware: str | None = None, **kw: Any) -> SensorMetadata:
    """The shipped OS0-64 calibration (derived: every other beam of a real OS-0-128);
    ``firmware`` (:data:`FIRMWARES`) sets the revisions that sensor reports, and the profile
    must be one it had."""
    if firmware is not None:
        fw = FIRMWARES.get(firmware)
        if fw is None:
            raise MetadataError(f"firmware {firmware!r}; emulated: {', '.join(FIRMWARES)}")
        if profile not in fw.profiles:
            raise MetadataError(f"udp_profile_lidar {profile}: firmware {firmware} had "
                                f"{', '.join(fw.profiles)}")
        kw = {"image_rev": fw.image_rev, "build_rev": fw.build_rev, **kw}
    cal = json.loads((resources.files(__package__) / "os0_64_calibration.json")
                     .read_text("utf-8"))
    w = parse_mode(mode)[0]
    shift = tuple(round(s * w / 1024) for s in cal["pixel_shift_by_row_1024"])
    kw = {"build_rev": cal["build_rev"], "image_rev": cal["image_rev"], **kw}
    return SensorMetadata(
        mode=mode, profile=profile, prod_line=cal["prod_line"], prod_pn=cal["prod_pn"],
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
