"""``tcf-hil detect`` and ``tcf-hil score``: the reference stem algorithm on a cloud, and
an observed forest scored against the ground truth."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
import numpy as np

from tcf_hil.cli._shared import console, floats, preset_option
from tcf_hil.errors import InputError


def read_cloud(path: Path) -> np.ndarray:
    """x, y, z of a PCD file as an (n, 3) float64 array; InputError names file and field."""
    from protocols.pcd import PcdError, decode_pcd

    try:
        data = path.read_bytes()
    except OSError as err:
        raise InputError(str(path), "", f"cannot read file ({err.strerror or err})") from err
    try:
        fields = decode_pcd(data)
    except PcdError as err:
        raise InputError(str(path), "", f"not a valid PCD file: {err}") from err
    for k in ("x", "y", "z"):
        if k not in fields:
            raise InputError(str(path), f"FIELDS.{k}",
                             f"the cloud has no {k} field (has: {', '.join(fields)})")
    xyz = np.column_stack([fields[k].astype(np.float64) for k in ("x", "y", "z")])
    bad = ~np.all(np.isfinite(xyz), axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InputError(str(path), f"point {i}", f"coordinates {xyz[i].tolist()} are not finite")
    return xyz


@click.command()
@click.argument("cloud", type=click.Path(dir_okay=False, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Observed-forest JSON to write.")
@preset_option("paper: exactly the published algorithm; tuned: refined; field: the field-grade "
               "program (edge returns, stems by shape, stem curve).")
@click.option("--curve-threshold", type=click.FloatRange(min=0, min_open=True), default=None,
              help="maxcurve (m) from which a stem is C (default 0.05, as the scenarios).")
@click.option("--other-threshold", type=click.FloatRange(min=0, min_open=True), default=None,
              help="maxcurve (m) from which a stem is X (default 0.25).")
@click.option("--scene-centre", callback=floats(2, "X,Y"), default="0,0", show_default=True,
              help="World x, y of the scene centre that d is measured from (the scenario's "
                   "origin, e.g. 500000,6900000 for a UTM plot).")
def detect(cloud: Path, out: Path, preset: str, curve_threshold: float | None,
           other_threshold: float | None, scene_centre: tuple[float, float]) -> None:
    """Run the reference stem algorithm on a PCD point cloud and write the observed JSON."""
    from tcf_hil._io import write_json_atomic
    from tcf_hil.sic import identify_stems, stem_params

    over: dict[str, Any] = {"scene_centre": tuple(scene_centre)}
    if curve_threshold is not None:
        over["curve_threshold_m"] = curve_threshold
    if other_threshold is not None:
        over["other_threshold_m"] = other_threshold
    try:
        prm = stem_params(preset, **over)
    except ValueError as err:
        raise click.BadParameter(str(err)) from err
    xyz = read_cloud(cloud)
    with console.status(f"stem algorithm on {len(xyz)} points"):
        doc = identify_stems(xyz, prm)
    write_json_atomic(out, doc)
    console.print(f"wrote {out}: {doc['total_objects_count']} stems")


@click.command()
@click.argument("gt", metavar="GT.json|INVENTORY.csv",
                type=click.Path(dir_okay=False, path_type=Path))
@click.argument("observed", metavar="OBSERVED.json",
                type=click.Path(dir_okay=False, path_type=Path))
@click.option("--match", "match_method", type=click.Choice(["greedy", "optimal"]),
              default="greedy", show_default=True,
              help="greedy: nearest pairs first (paper); optimal: minimum total distance.")
@click.option("--max-distance", type=click.FloatRange(min=0, min_open=True), default=1.0,
              show_default=True, help="Matching radius d in the x-y plane (m).")
@click.option("--weights", callback=floats(4, "S,C,X,N"), default="1,1,1,1",
              show_default=True, help="Class weights by ground-truth row.")
@click.option("--credits", callback=floats(3, "E,A,N"), default="1,0,0", show_default=True,
              help="Credits for exact, almost and no match.")
@click.option("--json", "json_out", type=click.Path(dir_okay=False, path_type=Path),
              default=None, help="Write every metric to this JSON file.")
@click.option("--plots", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Write em_heatmap.png and matched_positions.png into this directory.")
def score(gt: Path, observed: Path, match_method: str, max_distance: float,
          weights: tuple[float, ...], credits: tuple[float, ...], json_out: Path | None,
          plots: Path | None) -> None:
    """Score an observed forest (SIC output) against the ground truth.

    Any document with objects[].cp and class (S/C/X) or quality (1/2/3) can be scored as
    either side; h, dbh and maxcurve are used when present. The ground truth may be a field
    inventory CSV instead (header row; id, x, y required; z, dbh_m, height_m, class
    optional; coordinates in the frame the SIC publishes in): the metrics whose inputs it
    lacks are absent, not zero.
    """
    from tcf_hil._io import write_json_atomic
    from tcf_hil.evaluation import EvalConfig, evaluate, metrics_table, write_plots
    from tcf_hil.evaluation.scoring import blank_absent
    from tcf_hil.recording.inventory import is_inventory, read_inventory
    from tcf_hil.recording.stems_json import load_stems, stem_table

    try:
        cfg = EvalConfig(match=match_method, max_distance_m=max_distance,  # type: ignore[arg-type]
                         weights=weights, credits=credits)  # type: ignore[arg-type]
    except ValueError as err:
        raise click.BadParameter(str(err)) from err
    if is_inventory(gt):
        truth = read_inventory(gt)
        g = stem_table(truth, str(gt), "observed")
    else:
        truth, g = {}, load_stems(gt, "observed")
    o = load_stems(observed, "observed")
    ev = evaluate(g, o, cfg)
    blank_absent(ev.metrics, truth)
    console.print(metrics_table(ev, f"{observed.name} vs {gt.name} ({match_method}, "
                                    f"d = {max_distance:g} m)"))
    if json_out is not None:
        write_json_atomic(json_out, ev.metrics)
        console.print(f"wrote {json_out}")
    if plots is not None:
        for p in write_plots(ev, g, o, plots, observed.stem):
            console.print(f"wrote {p}")
