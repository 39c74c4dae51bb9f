"""Read and validate stems documents (ground truth and observed SIC output) into arrays.

Structure is checked against the published JSON Schemas in :mod:`protocols.stems` (compiled
once with fastjsonschema); then what a schema cannot say: finite numbers, unique ids, and
``class`` agreeing with ``quality`` when both are given. Every error is an
:class:`~tcf_hil.errors.InputError` naming the file and the field.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from functools import cache
from typing import Any, Literal

import fastjsonschema
import numpy as np
from numpy.typing import NDArray

from protocols.stems import CLASS_BY_QUALITY, QUALITY_BY_CLASS, load_schema
from tcf_hil._io import read_json
from tcf_hil.errors import InputError, short_repr

Kind = Literal["ground_truth", "observed"]
FloatArray = NDArray[np.float64]


@cache
def _validator(kind: Kind) -> Any:
    return fastjsonschema.compile(load_schema(kind))


def _field(name: str | None) -> str:
    name = name or "data"
    return name[len("data."):] if name.startswith("data.") else ("" if name == "data" else name)


@dataclass(frozen=True)
class StemTable:
    """A stems document as arrays (one row per object, in document order).

    ``h``, ``dbh`` and ``maxcurve`` are NaN where an observed document omits them.
    """

    source: str
    ids: list[Any]
    xyz: FloatArray
    classes: NDArray[np.str_]
    quality: NDArray[np.int64]
    h: FloatArray
    dbh: FloatArray
    maxcurve: FloatArray
    doc: dict[str, Any]

    def __len__(self) -> int:
        return len(self.ids)

    def sort_keys(self) -> list[tuple[Any, ...]]:
        """A total order of the objects that does not depend on their order in the document:
        integer ids, then string ids, then objects without an id by position and class."""
        out: list[tuple[Any, ...]] = []
        for i, oid in enumerate(self.ids):
            if oid is None:
                out.append((2, "", float(self.xyz[i, 0]), float(self.xyz[i, 1]),
                            str(self.classes[i])))
            elif isinstance(oid, str):
                out.append((1, oid, 0.0, 0.0, ""))
            else:
                out.append((0, oid, 0.0, 0.0, ""))
        return out


_MAX_COORD = 1e9  # metres: any projected coordinate system fits
_MAX_SIZE = 1e4  # metres: heights, diameters, curves


def _number(v: Any, source: str, field: str, limit: float) -> float:
    try:
        f = float(v)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f) or abs(f) > limit:
        raise InputError(source, field, f"{short_repr(v, 40)} is not a finite number within "
                                        f"+-{limit:g}")
    return f


def stem_table(doc: Any, source: str = "<memory>", kind: Kind = "observed") -> StemTable:
    """Validate a parsed stems document and return it as arrays.

    Raises:
        InputError: naming ``source`` and the offending field.
    """
    try:
        _validator(kind)(doc)
    except fastjsonschema.JsonSchemaValueException as err:
        msg = err.message
        if err.rule == "anyOf":
            msg = f"{_field(err.name)} needs one of the keys 'class' or 'quality'"
        elif err.name == "data":
            msg = msg.replace("data", "the document", 1)
        raise InputError(source, _field(err.name), msg.replace("data.", "")) from err
    objs = doc["objects"]
    n = len(objs)
    ids: list[Any] = []
    seen: dict[Any, int] = {}
    xyz = np.empty((n, 3))
    classes = np.empty(n, dtype="<U1")
    quality = np.empty(n, dtype=np.int64)
    extra = {k: np.full(n, np.nan) for k in ("h", "dbh", "maxcurve")}
    for i, o in enumerate(objs):
        # A missing id stays None (ordered by content when ranking); 1.0 and 1 are one
        # JSON number.
        oid = o.get("id")
        if isinstance(oid, float) and oid.is_integer():
            oid = int(oid)
        if oid is not None:
            key = (type(oid).__name__, oid)
            if key in seen:
                raise InputError(source, f"objects[{i}].id",
                                 f"duplicate id {oid!r} (also at objects[{seen[key]}])")
            seen[key] = i
        ids.append(oid)
        for j, v in enumerate(o["cp"]):
            xyz[i, j] = _number(v, source, f"objects[{i}].cp[{j}]", _MAX_COORD)
        for k, arr in extra.items():
            if k in o:
                arr[i] = _number(o[k], source, f"objects[{i}].{k}", _MAX_SIZE)
        c, q = o.get("class"), o.get("quality")
        if c is not None and q is not None and QUALITY_BY_CLASS[c] != q:
            raise InputError(source, f"objects[{i}].quality",
                             f"quality {q} disagrees with class {c!r} (expected "
                             f"{QUALITY_BY_CLASS[c]})")
        c = c if c is not None else CLASS_BY_QUALITY[q]
        classes[i] = c
        quality[i] = QUALITY_BY_CLASS[c]
    count = doc.get("total_objects_count")
    if count is not None and count != n:
        raise InputError(source, "total_objects_count",
                         f"says {count} but objects holds {n}")
    return StemTable(source, ids, xyz, classes, quality, extra["h"], extra["dbh"],
                     extra["maxcurve"], doc)


def load_stems(path: str | os.PathLike[str], kind: Kind = "observed") -> StemTable:
    """Read and validate a stems JSON file (see :func:`stem_table`)."""
    return stem_table(read_json(path), str(path), kind)
