"""A tcf-hil run directory: the names of the files a run writes, and the one check that a
directory holds the ones a reader needs (``tcf-hil export``, ``replay``, ``run --replay``),
with one line naming the missing file."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tcf_hil._io import read_json
from tcf_hil.errors import InputError

__all__ = ["RunDir"]


class RunDir:
    """The files of the run directory ``path`` (what exists depends on the run: a soak run
    records no lidar traffic, a field recording has an inventory instead of a ground truth)."""

    LIDAR = "lidar.pcap"
    LABELS = "lidar_labels.bin"
    METADATA = "metadata.json"
    MANIFEST = "manifest.json"
    POSES = "sensor_poses.csv"
    GROUND_TRUTH = "ground_truth.json"
    INVENTORY = "inventory.csv"
    SCORE = "score.json"
    REPORT = "report.html"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)

    def __truediv__(self, name: str) -> Path:
        return self.path / name

    def manifest(self) -> dict[str, Any]:
        """``manifest.json`` as a document (empty where the directory has none: a field
        recording, an offline capture)."""
        path = self.path / self.MANIFEST
        return read_json(path) if path.exists() else {}

    def require(self, *names: str, missing: str = "not a tcf-hil run directory") -> RunDir:
        """Self, where the directory exists and holds every one of ``names``; else an
        InputError naming the directory or the first file missing (``missing`` says what
        the directory then is not; a run that kept no lidar traffic is told as such)."""
        if not self.path.is_dir():
            raise InputError(str(self.path), "", "not a directory (a run directory is "
                             "expected)")
        for name in names:
            if not (self.path / name).exists():
                why = f"missing: {missing}"
                if name == self.LIDAR and (self.path / self.MANIFEST).exists():
                    why = "missing: this run did not record its lidar traffic (a soak run)"
                raise InputError(str(self.path / name), "", why)
        return self
