"""Load, validate, resolve and print scenarios (TOML).

A scenario file may start from a preset with ``extends = "forest-v"`` and override any key.
Validation is driven by the dataclasses in :mod:`tcf_hil.scenario._model`: an unknown key, a
wrong type or a value out of range raises :class:`~tcf_hil.errors.ConfigError` naming the key,
the value and what is allowed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import tomllib
import typing
from importlib import resources
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

from protocols.stems import CLASSES
from tcf_hil.errors import ConfigError
from tcf_hil.scenario._model import Scenario

T = TypeVar("T")

_ROMAN = ("i", "ii", "iii", "iv", "v", "vi", "vii", "viii", "ix", "x")
PRESET_NAMES: tuple[str, ...] = tuple(f"forest-{r}" for r in _ROMAN)
STAND_PRESETS: tuple[str, ...] = ("pine-thinning", "spruce-thinning", "birch-mixed",
                                  "spruce-final-felling")
"""Natural stands (``stand.kind = "natural"``), each parameter sourced in its file."""
NATURAL_VARIANTS: tuple[str, ...] = tuple(f"{p}-natural" for p in PRESET_NAMES)
"""Each paper forest with natural stems (``forest-v-natural``): its plot, count, placement,
DBH and class shares, ``natural-variant.toml`` laid over it."""
EXTRA_PRESETS: tuple[str, ...] = ("strip-road", *STAND_PRESETS, *NATURAL_VARIANTS)
"""Presets beyond the paper's forests (``strip-road``: Forest V cut by three strip roads,
driven in three passes; the natural stands and the paper forests' natural variants)."""
_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")

_MAX_ITEMS = 1000


def _describe_type(tp: Any) -> str:
    if dataclasses.is_dataclass(tp):
        return "a table"
    origin = get_origin(tp)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) for a in get_args(tp))
    if origin is tuple:
        args = get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list (up to {_MAX_ITEMS} items) of {_describe_type(args[0])}"
        return f"an array of {len(args)} numbers"
    return {int: "an integer", float: "a number", str: "a string", bool: "true or false"}.get(
        tp, str(tp))


def _limits_text(meta: typing.Mapping[str, Any]) -> str:
    parts = []
    if "gt" in meta:
        parts.append(f"> {meta['gt']}")
    if "ge" in meta:
        parts.append(f">= {meta['ge']}")
    if "le" in meta:
        parts.append(f"<= {meta['le']}")
    return " and ".join(parts)


def _check_number(value: Any, key: str, tp: type, meta: typing.Mapping[str, Any],
                  source: str | None) -> float | int:
    allowed = _describe_type(tp)
    lim = _limits_text(meta)
    if lim:
        allowed = f"{allowed} {lim}"
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ConfigError(key, value, allowed, source)
    if tp is int and not isinstance(value, int):
        raise ConfigError(key, value, allowed, source)
    if isinstance(value, float) and not math.isfinite(value):
        raise ConfigError(key, value, allowed, source)
    if ("gt" in meta and not value > meta["gt"]) or ("ge" in meta and not value >= meta["ge"]) \
            or ("le" in meta and not value <= meta["le"]):
        raise ConfigError(key, value, allowed, source)
    if tp is int:
        return int(value)
    try:
        return float(value)
    except OverflowError as err:  # an integer beyond the float range
        raise ConfigError(key, value, f"{allowed} (within the float range)", source) from err


def _convert(tp: Any, value: Any, key: str, meta: typing.Mapping[str, Any],
             source: str | None) -> Any:
    if dataclasses.is_dataclass(tp):
        return _build(tp, value, key + ".", source)  # type: ignore[arg-type]
    origin = get_origin(tp)
    if origin is Literal:
        choices = get_args(tp)
        if value not in choices:
            raise ConfigError(key, value, _describe_type(tp), source)
        return value
    if origin is tuple and len(get_args(tp)) == 2 and get_args(tp)[1] is Ellipsis:
        if not isinstance(value, list | tuple) or len(value) > _MAX_ITEMS:
            raise ConfigError(key, value, _describe_type(tp), source)
        return tuple(_convert(get_args(tp)[0], v, f"{key}[{i}]", meta, source)
                     for i, v in enumerate(value))
    if origin is tuple:
        args = get_args(tp)
        if not isinstance(value, list | tuple) or len(value) != len(args):
            raise ConfigError(key, value, _describe_type(tp), source)
        return tuple(_check_number(v, f"{key}[{i}]", a, meta, source)
                     for i, (v, a) in enumerate(zip(value, args, strict=True)))
    if tp is str:
        if not isinstance(value, str):
            raise ConfigError(key, value, "a string", source)
        return value
    if tp in (int, float):
        return _check_number(value, key, tp, meta, source)
    if tp is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, value, "true or false", source)
        return value
    raise TypeError(f"unsupported scenario field type {tp!r} at {key}")  # a bug in _model


def _build(cls: type[T], data: Any, prefix: str, source: str | None) -> T:
    where = prefix.rstrip(".") or "<top level>"
    if not isinstance(data, dict):
        raise ConfigError(where, data, "a table", source)
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for name in data:
        if name not in fields:
            raise ConfigError(prefix + name, data[name],
                              f"no such key; keys here: {', '.join(fields)}", source)
    kwargs = {name: _convert(hints[name], data[name], prefix + name, fields[name].metadata, source)
              for name in data}
    return cls(**kwargs)


def _validate(s: Scenario, source: str | None) -> None:
    """Checks that involve more than one key."""
    def bad(key: str, value: object, allowed: str) -> ConfigError:
        return ConfigError(key, value, allowed, source)

    if not _NAME_RE.match(s.name):
        raise bad("name", s.name, "1-64 characters of letters, digits, '-', '_', '.'")
    if not s.timestamp.strip():
        raise bad("timestamp", s.timestamp, "a non-empty string")
    from emulators.lidar import SIGNAL_MULTIPLIERS

    if s.sensor.signal_multiplier not in SIGNAL_MULTIPLIERS:
        raise bad("sensor.signal_multiplier", s.sensor.signal_multiplier,
                  "one of " + ", ".join(f"{v:g}" for v in SIGNAL_MULTIPLIERS))
    st = s.stems
    for key, (lo, hi) in (("stems.height_m", st.height_m), ("stems.lean_deg", st.lean_deg),
                          ("stems.sweep_m.S", st.sweep_m.S), ("stems.sweep_m.C", st.sweep_m.C),
                          ("stems.sweep_m.X", st.sweep_m.X)):
        if lo > hi:
            raise bad(key, [lo, hi], "[low, high] with low <= high")
    d = st.dbh
    if d.min_m > d.max_m:
        raise bad("stems.dbh.min_m", d.min_m, f"<= stems.dbh.max_m ({d.max_m})")
    if d.kind in ("normal", "lognormal", "fixed") and not d.min_m <= d.mean_m <= d.max_m:
        raise bad("stems.dbh.mean_m", d.mean_m, f"within [{d.min_m}, {d.max_m}] (min_m, max_m)")
    if st.top_diameter_m >= d.min_m:
        raise bad("stems.top_diameter_m", st.top_diameter_m,
                  f"< stems.dbh.min_m ({d.min_m})")
    if st.curve_threshold_m >= st.other_threshold_m:
        raise bad("stems.curve_threshold_m", st.curve_threshold_m,
                  f"< stems.other_threshold_m ({st.other_threshold_m})")
    sw = st.sweep_m
    if sw.S[1] >= st.curve_threshold_m:
        raise bad("stems.sweep_m.S", list(sw.S),
                  f"a range below stems.curve_threshold_m ({st.curve_threshold_m})")
    if not (sw.C[0] >= st.curve_threshold_m and sw.C[1] < st.other_threshold_m):
        raise bad("stems.sweep_m.C", list(sw.C),
                  f"a range within [{st.curve_threshold_m}, {st.other_threshold_m}) "
                  "(curve_threshold_m, other_threshold_m)")
    if sw.X[0] < st.other_threshold_m:
        raise bad("stems.sweep_m.X", list(sw.X),
                  f"a range at or above stems.other_threshold_m ({st.other_threshold_m})")
    mix = [getattr(st.class_mix, c) for c in CLASSES]
    if st.count > 0 and sum(mix) <= 0:
        raise bad("stems.class_mix", dict(zip(CLASSES, mix, strict=True)),
                  "at least one class with a share > 0")
    _validate_stand(s, bad)
    dist = s.distribution
    for axis, size in zip("xy", s.plot.size_m, strict=True):
        if 2 * dist.edge_margin_m >= size:
            raise bad("distribution.edge_margin_m", dist.edge_margin_m,
                      f"less than half the plot's {axis} size ({size / 2})")
    t = s.track
    if dist.corridor_half_width_m > 0 and t.start_m[:2] != t.end_m[:2] \
            and t.start_m[0] != t.end_m[0] and t.start_m[1] != t.end_m[1]:
        raise bad("distribution.corridor_half_width_m", dist.corridor_half_width_m,
                  "0 unless the track runs parallel to the x or y axis")


def _validate_stand(s: Scenario, bad: Any) -> None:
    """The ``[stand]`` table's checks across keys (natural stands only)."""
    sd = s.stand
    if sd.kind != "natural":
        return
    species = ("pine", "spruce", "birch")
    if s.stems.count > 0 and sum(getattr(sd, n).share for n in species) <= 0:
        raise bad("stand.pine.share", sd.pine.share,
                  "a share > 0 for at least one of stand.pine, stand.spruce, stand.birch")
    for n in species:
        cfg = getattr(sd, n)
        mean = cfg.dbh_mean_m or s.stems.dbh.mean_m
        if cfg.share > 0 and s.stems.dbh.kind in ("normal", "lognormal", "fixed", "weibull") \
                and not s.stems.dbh.min_m <= mean <= s.stems.dbh.max_m:
            raise bad(f"stand.{n}.dbh_mean_m", cfg.dbh_mean_m,
                      f"within [{s.stems.dbh.min_m}, {s.stems.dbh.max_m}] "
                      "(stems.dbh.min_m, max_m)")
    if s.stems.dbh.kind == "weibull" and s.stems.dbh.sd_m <= 0:
        raise bad("stems.dbh.sd_m", s.stems.dbh.sd_m, "> 0 for a weibull distribution")
    ranges = [("stand.suppressed_dbh_m", sd.suppressed_dbh_m)]
    for f in dataclasses.fields(sd.defects):
        v = getattr(sd.defects, f.name)
        if isinstance(v, tuple):
            ranges.append((f"stand.defects.{f.name}", v))
    for key, (lo, hi) in ranges:
        if lo > hi:
            raise bad(key, [lo, hi], "[low, high] with low <= high")
    x_shares = [getattr(sd.defects, f"x_{k}") for k in
                ("sweep", "crook", "fork", "broken_top", "double_stem")]
    if s.stems.class_mix.X > 0 and sum(x_shares) <= 0:
        raise bad("stand.defects.x_crook", sd.defects.x_crook,
                  "a share > 0 for at least one stand.defects.x_* (X stems need a defect)")


def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def preset_name(name: str) -> str | None:
    """Return the canonical preset name for ``name`` (``forest-v``, ``V``, ``Forest_V``...)."""
    n = name.strip().lower().replace("_", "-").replace(" ", "-")
    if n in _ROMAN:
        n = f"forest-{n}"
    if n.endswith("-natural") and n.removesuffix("-natural") in _ROMAN:
        n = f"forest-{n}"
    return n if n in PRESET_NAMES or n in EXTRA_PRESETS else None


def _preset_text(name: str) -> str:
    return (resources.files("tcf_hil.scenario") / "presets" / f"{name}.toml").read_text("utf-8")


def _load_dict(name_or_path: str, _seen: tuple[str, ...] = ()) -> tuple[dict[str, Any], str]:
    preset = preset_name(name_or_path)
    path = Path(name_or_path)
    if preset in NATURAL_VARIANTS and "/" not in name_or_path \
            and not name_or_path.endswith(".toml"):
        paper = preset.removesuffix("-natural")
        base, _ = _load_dict(paper, _seen)
        over = tomllib.loads(_preset_text("natural-variant"))
        data = _merge(base, over)
        data["name"] = preset
        data["description"] = (f"{base.get('description', paper)}; natural stems, branches, "
                               "foliage and understory")
        return data, f"preset {preset}"
    # A bare preset name is the preset, even if a file of that name sits in the working
    # directory; write ./forest-v or forest-v.toml to mean a file.
    looks_like_path = "/" in name_or_path or name_or_path.endswith(".toml")
    if preset is not None and not looks_like_path:
        source, text = f"preset {preset}", _preset_text(preset)
    else:
        source = str(path)
        try:
            text = path.read_text("utf-8")
        except FileNotFoundError as err:
            raise ConfigError("scenario", name_or_path,
                              f"a TOML file or a preset ({', '.join(PRESET_NAMES)})") from err
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError("scenario", name_or_path, f"a readable UTF-8 file ({err})") from err
    try:
        data = tomllib.loads(text)
    except ValueError as err:  # TOMLDecodeError, or an integer beyond the digit limit
        raise ConfigError("<toml>", source, f"valid TOML ({str(err).splitlines()[0]})",
                          source) from err
    except RecursionError as err:
        raise ConfigError("<toml>", source, "valid TOML (nested too deeply)", source) from err
    ext = data.pop("extends", None)
    if ext is not None:
        if not isinstance(ext, str) or preset_name(ext) is None:
            raise ConfigError("extends", ext, f"a preset name ({', '.join(PRESET_NAMES)})",
                              source)
        if ext in _seen:
            raise ConfigError("extends", ext, "a preset that does not extend itself", source)
        base, _ = _load_dict(preset_name(ext) or ext, (*_seen, ext))  # a preset, never a file
        data = _merge(base, data)
    return data, source


def _sensor_preset(data: dict[str, Any], source: str | None) -> dict[str, Any]:
    """``data`` with its ``[sensor]`` table laid over the preset it names."""
    from emulators.lidar import SENSOR_PRESETS

    sensor = data.get("sensor")
    if not isinstance(sensor, dict) or "preset" not in sensor:
        return data
    name = sensor["preset"]
    if not isinstance(name, str) or name not in SENSOR_PRESETS:
        raise ConfigError("sensor.preset", name, "one of " + ", ".join(
            repr(n) for n in SENSOR_PRESETS), source)
    return {**data, "sensor": _merge(dataclasses.asdict(SENSOR_PRESETS[name]), sensor)}


def with_sensor(scn: Scenario, preset: str | None) -> Scenario:
    """``scn`` with the named sensor preset instead of its own ``[sensor]`` (None: as it
    is): what ``--sensor PRESET`` does."""
    from emulators.lidar import SENSOR_PRESETS

    if preset is None:
        return scn
    if preset not in SENSOR_PRESETS:
        raise ConfigError("--sensor", preset, "one of " + ", ".join(SENSOR_PRESETS))
    return dataclasses.replace(scn, sensor=SENSOR_PRESETS[preset])


def scenario_from_dict(data: dict[str, Any], source: str | None = None) -> Scenario:
    """Validate a parsed TOML document into a :class:`Scenario`."""
    scn = _build(Scenario, _sensor_preset(data, source), "", source)
    _validate(scn, source)
    return scn


def load_scenario(name_or_path: str, *, seed: int | None = None) -> Scenario:
    """Load a preset name (``forest-v``, ``V``) or a TOML file into a validated Scenario.

    Args:
        name_or_path: preset name or path to a ``.toml`` file.
        seed: overrides the scenario's ``seed`` when given.

    Raises:
        ConfigError: naming the key, the bad value and what is allowed.
    """
    data, source = _load_dict(name_or_path)
    if seed is not None:
        data["seed"] = seed
    return scenario_from_dict(data, source)


def scenario_to_dict(scn: Scenario) -> dict[str, Any]:
    """The fully resolved scenario as plain TOML-able data (tuples become lists)."""
    def conv(v: Any) -> Any:
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        if isinstance(v, tuple | list):
            return [conv(x) for x in v]
        return v
    out: dict[str, Any] = conv(dataclasses.asdict(scn))
    return out


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):  # TOML basic strings also forbid a raw DEL, which JSON allows
        return json.dumps(v, ensure_ascii=False).replace("\x7f", "\\u007f")
    if isinstance(v, tuple | list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {v!r} as TOML")


def _toml_table(obj: Any, header: str, out: list[str]) -> None:
    nested = []
    if header:
        out.append(f"\n[{header}]")
    for f in dataclasses.fields(obj):
        v = getattr(obj, f.name)
        if dataclasses.is_dataclass(v):
            nested.append((f.name, v))
            continue
        doc = f.metadata.get("doc", "")
        line = f"{f.name} = {_toml_value(v)}"
        out.append(f"{line:<40} # {doc}" if doc else line)
    for name, v in nested:
        _toml_table(v, f"{header}.{name}" if header else name, out)


def scenario_to_toml(scn: Scenario) -> str:
    """The fully resolved scenario as commented TOML; loading it gives back an equal Scenario."""
    out = [f"# tcf-hil scenario {scn.name}, fully resolved (every key, with its default)"]
    _toml_table(scn, "", out)
    return "\n".join(out) + "\n"


def list_presets() -> list[Scenario]:
    """All Forest I–X presets, resolved."""
    return [load_scenario(n) for n in PRESET_NAMES]


