"""``tcf-hil export``: a run's cloud and stems in the files forestry and GIS tools read."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import click

from tcf_hil.cli._shared import Progress, console, err_console


@click.command("export")
@click.argument("run_dir", type=click.Path(path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), required=True,
              help="File to write; its suffix picks what and how: .las .laz .ply .pcd (the "
                   "cloud), .geojson .csv (the stems), .mcap (the whole run for Foxglove: "
                   "cloud, transforms, track, stems, score over time), .osf (Ouster's own "
                   "format, written by ouster-sdk); no suffix (run_bag/): "
                   "a ROS 2 bag folder (rosbag2, MCAP storage) that ouster-ros plays.")
@click.option("--every", type=click.IntRange(min=1), default=1, show_default=True,
              help="Cloud: keep every N-th frame (a long run's cloud is large; 10 keeps one "
                   "frame a second at 10 Hz).")
@click.option("--stems", type=click.Choice(["both", "truth", "sic"]), default="both",
              show_default=True,
              help="Stems: the ground truth, the SIC's scored forest, or both (a 'source' "
                   "column tells them apart).")
@click.option("--epsg", type=click.IntRange(min=1), default=None,
              help="The coordinate system of the scenario's origin (e.g. 3067 for "
                   "ETRS-TM35FIN): LAS/LAZ get the OGC WKT record (from PROJ's database), "
                   "GeoJSON the 'crs' member QGIS and GDAL read. PLY, PCD and CSV have no "
                   "place for one.")
def export_cmd(run_dir: Path, out: Path, every: int, stems: str, epsg: int | None) -> None:
    """Export a run directory for CloudCompare, lidR, 3DFin, QGIS and the like.

    \b
    The cloud (.las/.laz LAS 1.4, .ply, .pcd): every return as the sensor sent it, in world
    coordinates (the scenario's origin included; LAS at 1 mm scale), with GPS time,
    intensity (reflectivity), return number, classification (2 ground, 64 stem, 5 branches
    and foliage, 3 understory, 1 dead wood, stumps and boulders, 7 noise) and the extra
    dimensions stem_id (the ground-truth tree), component and ring.
    The stems (.geojson/.csv): every ground-truth stem and every stem the SIC published last,
    with its outcome (correct, misclassified, missed_seen, missed_unseen; matched,
    false_positive), DBH and height true and observed, and its distance from the track.

    The run for Foxglove (.mcap): every frame's cloud coloured by what it hit, the sensor's
    pose (/tf), the track, the ground-truth stems and each of the SIC's publications as
    cylinders coloured by outcome, and its score, at the times they had in the run (the
    topics: README, "Foxglove"), and beside it NAME.layout.json, a Foxglove layout for it
    (Layouts, Import from file).

    A ROS 2 bag (a folder: --out run_bag): the Ouster packets as ouster-ros records them
    (/ouster/lidar_packets, /ouster/imu_packets, /ouster/metadata), the cloud as
    sensor_msgs/PointCloud2, /tf, the harvester's pose, the stems as MarkerArrays and the CAN
    frames; ros2 bag play and ouster-ros's replay read it, tcf-hil replay too.

    \b
    Examples:
      tcf-hil export runs/forest-v --out forest-v.mcap
      tcf-hil export runs/forest-v --out forest-v_bag
      tcf-hil export runs/forest-v --out forest-v.laz --epsg 3067
      tcf-hil export runs/forest-v --out stems.geojson --epsg 3067
      tcf-hil export runs/forest-v --out stems.csv --stems truth
    """
    from tcf_hil.results.export import export

    suffix = out.suffix.lower()
    if epsg is not None and suffix not in (".las", ".laz", ".geojson"):
        raise click.BadParameter(f"applies to .las, .laz and .geojson ({suffix or 'a bag'} "
                                 "has no place for a coordinate system)", param_hint="--epsg")
    if suffix in ("", ".osf", ".mcap"):  # the whole run, for ROS 2, ouster-sdk or Foxglove
        with Progress(f"export {out.name}", total=None, keep=False) as bar:
            console.print(_whole_run(run_dir, out, every, bar.counter))
        return
    with Progress(f"export {out.name}", total=None, keep=False) as bar:
        r = export(run_dir, out, every=every, stems=stems, epsg=epsg, progress=bar.counter)
    if r.kind == "cloud":
        console.print(f"{r.count:,} points -> {r.path}")
        if not r.labelled:
            err_console.print(f"Note: {run_dir} has no lidar_labels.bin (recorded before "
                              "tcf-hil wrote it): classification 1, stem_id 0.")
        if r.unlabelled_frames:
            err_console.print(f"Note: {r.unlabelled_frames} frame(s) of the capture had no "
                              "label record (a run cut short while writing): classification "
                              "0, component 255.")
        if not r.gps_adjusted and suffix in (".las", ".laz"):
            err_console.print(f"Note: {run_dir} has no run manifest tying its clock to UTC: "
                              "GPS time is simulation seconds (GPS week time).")
    else:
        console.print(f"{r.count:,} stems -> {r.path}")


def _whole_run(run_dir: Path, out: Path, every: int, progress: Any) -> str:
    """Write the whole run as a ROS 2 bag (no suffix), an OSF or an MCAP file for Foxglove;
    the line that says what was written."""
    suffix = out.suffix.lower()
    if not suffix:
        from tcf_hil.results.rosbag import write_bag

        b = write_bag(run_dir, out, every=every, progress=progress)
        return (f"{b.packets:,} packets, {b.frames:,} clouds, {b.messages:,} messages -> "
                f"{b.path}/ (ros2 bag play {b.path})")
    if suffix == ".osf":
        from tcf_hil.results.osf import write_osf

        o = write_osf(run_dir, out, progress=progress)
        return f"{o.frames:,} frames -> {o.path} (ouster-cli source {o.path} info)"
    from tcf_hil.results.foxglove import write_mcap

    m = write_mcap(run_dir, out, every=every, progress=progress)
    return (f"{m.frames:,} frames ({m.points:,} points), {m.publications} publications -> "
            f"{m.path} (Foxglove layout: {m.layout})")
