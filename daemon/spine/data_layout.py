"""Where things live in the data folder (config.data_dir): the recorder's segments at its top, the mapping worker's
map in `map/`, and the latest map previews the status server serves in `map/previews/`."""

from __future__ import annotations

from pathlib import Path

PREVIEWS = ("rgb", "semantics", "elevation")  # the preview images, each `<name>.png`


def preview_dir(data_folder: Path) -> Path:
    """Where the mapping worker writes its latest previews (and the status server reads them)."""
    return Path(data_folder) / "map" / "previews"
