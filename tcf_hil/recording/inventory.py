"""A field inventory as ground truth: a CSV of measured trees, for ``score`` and for runs on
field recordings, in place of a generated forest's ``ground_truth.json``.

The CSV has a header row; ``id``, ``x`` and ``y`` are required, ``z``, ``dbh_m``,
``height_m`` and ``class`` (S, C or X) optional; other columns are ignored, an empty cell
is a value not measured. Coordinates are metres in the projected frame the onboard program
publishes in (e.g. UTM: the harvester's CAN datum puts its map there); matching is in x-y, so
``z`` only describes. Metrics whose inputs the inventory lacks (DBH without ``dbh_m``, height
without ``height_m``, every class metric and the EM without a class for every tree,
maxcurve always) are absent from the score (``null`` in score.json, "absent" in tables),
never zero. An inventory knows nothing of what the sensor saw: its trees all count as seen,
so the seen/all split is the same table twice.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Any

from tcf_hil.errors import InputError

__all__ = ["INVENTORY_COLUMNS", "absent_metrics", "is_inventory", "load_truth",
           "read_inventory"]

INVENTORY_COLUMNS = ("id", "x", "y", "z", "dbh_m", "height_m", "class")
_REQUIRED = ("id", "x", "y")
_MAX_COORD = 1e9
_MAX_SIZE = 1e4

#: metrics that need each optional column (or the observed side's values against it)
_NEEDS: dict[str, tuple[str, ...]] = {
    "dbh_m": ("dbh_rmse_m", "dbh_bias_m"),
    "height_m": ("height_rmse_m", "height_bias_m"),
    "class": ("evaluation_score_percent", "quality_correct_percent", "quality_error_percent",
              "rmse_quality", "correct_matches", "wrong_matches", "accuracy_percent",
              "misclassified_percent"),
    "maxcurve": ("maxcurve_rmse_m", "maxcurve_bias_m"),
}


def is_inventory(path: Path) -> bool:
    return path.suffix.lower() == ".csv"


def read_inventory(path: Path) -> dict[str, Any]:
    """The inventory as a stems document (``objects`` with ``id``, ``cp``, ``class``, and
    ``dbh``/``h`` where measured) plus ``inventory``: its source, columns and the metrics it
    cannot give. InputError names the file, the line and the column."""
    src = str(path)
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as err:
        raise InputError(src, "", f"cannot read the inventory: {err}") from err
    except csv.Error as err:
        raise InputError(src, "", f"not a CSV file: {err}") from err
    if not rows:
        raise InputError(src, "", "empty: an inventory needs a header row (id,x,y,...)")
    head = [h.strip().lower() for h in rows[0]]
    for name in _REQUIRED:
        if name not in head:
            raise InputError(src, "line 1", f"the header has no {name!r} column (it has "
                             f"{', '.join(head) or 'nothing'}; id, x and y are required, "
                             "z, dbh_m, height_m and class optional)")
    dup = sorted({h for h in head if head.count(h) > 1 and h in INVENTORY_COLUMNS})
    if dup:
        raise InputError(src, "line 1", f"column {dup[0]!r} appears twice")
    col = {name: head.index(name) for name in INVENTORY_COLUMNS if name in head}
    objects: list[dict[str, Any]] = []
    seen: dict[str, int] = {}
    for line, row in enumerate(rows[1:], 2):
        if not any(c.strip() for c in row):
            continue  # a blank line

        def cell(name: str, row: list[str] = row) -> str:
            i = col.get(name)
            return row[i].strip() if i is not None and i < len(row) else ""

        def number(name: str, limit: float, line: int = line) -> float | None:
            text = cell(name)
            if not text:
                if name in _REQUIRED:
                    raise InputError(src, f"line {line}, column {name}", "empty; required")
                return None
            try:
                v = float(text)
            except ValueError:
                v = math.nan
            if not math.isfinite(v) or abs(v) > limit:
                raise InputError(src, f"line {line}, column {name}",
                                 f"{text!r} is not a finite number within +-{limit:g}")
            return v

        oid = cell("id")
        if not oid:
            raise InputError(src, f"line {line}, column id", "empty; every tree needs an id")
        if oid in seen:
            raise InputError(src, f"line {line}, column id",
                             f"duplicate id {oid!r} (also on line {seen[oid]})")
        seen[oid] = line
        x, y = number("x", _MAX_COORD), number("y", _MAX_COORD)
        z = number("z", _MAX_COORD)
        o: dict[str, Any] = {"id": int(oid) if oid.isdecimal() else oid,
                             "cp": [x, y, 0.0 if z is None else z]}
        cls = cell("class").upper()
        if cls and cls not in ("S", "C", "X"):
            raise InputError(src, f"line {line}, column class",
                             f"{cell('class')!r}; expected S, C or X")
        o["class"] = cls
        for name, key in (("dbh_m", "dbh"), ("height_m", "h")):
            v = number(name, _MAX_SIZE)
            if v is not None and v < 0:
                raise InputError(src, f"line {line}, column {name}",
                                 f"{cell(name)!r} is negative")
            if v is not None:
                o[key] = v
        objects.append(o)
    absent = [name for name, key in (("dbh_m", "dbh"), ("height_m", "h"))
              if not any(key in o for o in objects)]
    if not all(o["class"] for o in objects):  # the EM needs every tree's class
        absent.append("class")
    for o in objects:
        o["class"] = o["class"] or "S"  # (no class: the class metrics are absent, not judged)
    return {"objects": objects, "total_objects_count": len(objects),
            "inventory": {"source": src, "columns": [h for h in head if h in col],
                          "absent": absent + ["maxcurve"]}}


def absent_metrics(truth: dict[str, Any]) -> list[str]:
    """The metric keys a ground truth cannot give (an inventory's missing columns)."""
    inv = truth.get("inventory")
    if not isinstance(inv, dict):
        return []
    return [m for name in inv.get("absent", ()) for m in _NEEDS.get(name, ())]


def load_truth(path: Path) -> dict[str, Any]:
    """Ground truth from a generated forest's ``ground_truth.json`` or a field inventory
    CSV (:func:`read_inventory`)."""
    if is_inventory(path):
        return read_inventory(path)
    from tcf_hil._io import read_json

    doc: dict[str, Any] = read_json(path)
    return doc
