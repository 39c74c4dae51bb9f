"""``tcf-hil scenario`` and ``tcf-hil forest``: the scenarios, and the synthetic forests
and surface-sampled clouds made from them."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.table import Table

from tcf_hil.cli._shared import Group, blame, console, seed_option


@click.group(cls=Group)
def scenario() -> None:
    """List and show scenarios (the Forest I-X presets or your own TOML files)."""


@scenario.command("list")
def scenario_list() -> None:
    """List the presets with their plot, stems, distribution and terrain."""
    from tcf_hil.scenario import list_presets

    t = Table(title="Scenario presets (paper, section 2.2)")
    for col in ("name", "plot (m)", "stems", "distribution", "terrain", "seed"):
        t.add_column(col)
    for s in list_presets():
        t.add_row(s.name, f"{s.plot.size_m[0]:g} x {s.plot.size_m[1]:g}", str(s.stems.count),
                  s.distribution.kind, s.terrain.kind, str(s.seed))
    console.print(t)
    from tcf_hil.scenario import EXTRA_PRESETS, NATURAL_VARIANTS, load_scenario

    for name in EXTRA_PRESETS:
        if name not in NATURAL_VARIANTS:
            console.print(f"Also [bold]{name}[/]: {load_scenario(name).description}.")
    console.print(f"Also [bold]{NATURAL_VARIANTS[0]}[/] ... [bold]{NATURAL_VARIANTS[-1]}[/]: "
                  "each paper forest (its plot, count, placement, DBH and classes) with "
                  "natural stems, branches, foliage and understory.")
    console.print("Show one fully resolved: [bold]tcf-hil scenario show forest-v[/]. "
                  "Start your own"
                  " from a preset with [bold]extends = \"forest-v\"[/] in a TOML file.")


@scenario.command("show")
@click.argument("name")
@seed_option()
def scenario_show(name: str, seed: int | None) -> None:
    """Print the fully resolved TOML of a preset or scenario file NAME."""
    from tcf_hil.scenario import load_scenario, scenario_to_toml

    click.echo(scenario_to_toml(load_scenario(name, seed=seed)), nl=False)


@click.group(cls=Group)
def forest() -> None:
    """Generate synthetic forests (SFC) and surface-sampled point clouds."""


def _terrain_kind(terrain: Any) -> str:
    shape = "flat" if not len(terrain.waves) else "rolling"
    return shape if terrain.tilt == (0.0, 0.0) else f"{shape} hillside"


@forest.command("generate")
@click.argument("scenario_name", metavar="PRESET_OR_TOML")
@seed_option("Random seed (default: the scenario's). Same scenario + seed = same bytes.")
@click.option("--out", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Output directory.")
@click.option("--no-meshes", is_flag=True, help="Skip stems.ply and terrain.ply.")
@click.option("--scenery", is_flag=True,
              help="Natural stands: also write scenery.ply (branches, foliage, understory, "
                   "dead wood, stumps, boulders; large: about 0.5 GB a hectare).")
def forest_generate(scenario_name: str, seed: int | None, out: Path, no_meshes: bool,
                    scenery: bool) -> None:
    """Generate a forest: ground_truth.json, stems.ply, terrain.ply and map.png in --out.

    stems.ply has a per-face stem_id (the ground-truth id); coordinates are world metres.
    A natural stand (pine-thinning, forest-v-natural, ...: `tcf-hil scenario list`) also
    lists its species, defects and ground objects in ground_truth.json; --scenery writes
    its branches, foliage and ground objects too.

    \b
    Examples:
      tcf-hil forest generate forest-v --out forest-v/
      tcf-hil forest generate pine-thinning --scenery --out pine/
    """
    from tcf_hil.scenario import load_scenario
    from tcf_hil.world.forest import generate_forest
    from tcf_hil.world.forest.output import write_forest

    scn = load_scenario(scenario_name, seed=seed)
    with blame(scenario_name), \
            console.status(f"generating {scn.name} ({scn.stems.count} stems)") as status:
        f = generate_forest(scn)
        paths = write_forest(f, out, meshes=not no_meshes, scenery=scenery,
                             progress=lambda name: status.update(f"{scn.name}: writing {name}"))
    counts = {c: int(np.sum(f.classes == c)) for c in ("S", "C", "X")}
    console.print(f"{scn.name}, seed {f.seed}: {len(f.stems)} stems "
                  f"(S {counts['S']}, C {counts['C']}, X {counts['X']}), terrain "
                  f"{_terrain_kind(f.terrain)}")
    for p in paths:
        console.print(f"  wrote {p}")


@forest.command("sample")
@click.argument("scenario_name", metavar="PRESET_OR_TOML")
@seed_option("Random seed.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), required=True,
              help="Output .pcd file (binary; x y z float64, stem_id uint32, 0 = terrain).")
@click.option("--points-per-stem", type=click.IntRange(min=0), default=None,
              help="Surface points per stem (default: scenario, paper 1000).")
@click.option("--terrain-density", type=click.FloatRange(min=0), default=None,
              help="Terrain points per m² (default: scenario).")
@click.option("--ground-truth", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Also write the ground truth JSON here.")
@click.option("--float32", is_flag=True,
              help="x y z as float32 (for open3d's legacy reader; loses precision far from 0).")
def forest_sample(scenario_name: str, seed: int | None, out: Path, points_per_stem: int | None,
                  terrain_density: float | None, ground_truth: Path | None,
                  float32: bool) -> None:
    """Surface-sample a forest (the paper's point clouds without lidar) into a PCD file."""
    from tcf_hil._io import write_bytes_atomic, write_json_atomic
    from tcf_hil.scenario import load_scenario
    from tcf_hil.world.forest import generate_forest
    from tcf_hil.world.forest import ground_truth as gt_doc
    from tcf_hil.world.forest.sampling import sample_surfaces

    scn = load_scenario(scenario_name, seed=seed)
    with blame(scenario_name), console.status(f"sampling {scn.name}"):
        f = generate_forest(scn)
        cloud = sample_surfaces(f, points_per_stem, terrain_density)
        write_bytes_atomic(out, cloud.to_pcd(float32=float32))
        if ground_truth is not None:
            write_json_atomic(ground_truth, gt_doc(f))
    console.print(f"wrote {out}: {len(cloud)} points "
                  f"({int(np.sum(cloud.stem_id > 0))} on stems)")
