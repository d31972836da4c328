"""The fleet's tile store: plain files under one folder, one sub-folder per global tile (geodetic_grid.TileId),
holding what each window of each drive contributed there, and the merged tile of all drives.

    tiles/<tile id>/<drive id>.w<window>.npz   the contribution's cells (Contribution's arrays)
    tiles/<tile id>/<drive id>.w<window>.json  what it is: drive, window, cameras, cells observed, semantics
    merged/<tile id>.npz, merged/<tile id>.json the fusion of every drive there (mapping.fleet.drive_merge)

Every file is written to a temporary name and moved into place; a contribution's .json is written after its
.npz and a contribution counts only once its .json is there. Writing the same window again replaces its files
with the same content: two workers that both ran a window leave one contribution, never two.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from mapping.fleet.geodetic_grid import TileId


@dataclass
class Contribution:
    """What one window of one drive saw in one tile, on the tile's cells (row, column), all (n, n[, ...])."""

    drive: str
    window: int
    height: np.ndarray  # float32 ellipsoidal height (WGS84), m; NaN where the window did not map the cell
    weight: np.ndarray  # float32 confidence of the cell (log(1 + supervising steps)), 0 where unmapped
    class_prob: np.ndarray | None  # uint8 class probabilities * 255 (n, n, classes); None: no semantics
    rgb: dict[str, np.ndarray]  # camera -> uint8 (n, n, 3)

    @property
    def name(self) -> str:
        return f"{self.drive}.w{self.window}"


@dataclass(frozen=True)
class ContributionInfo:
    """A contribution's .json."""

    drive: str
    window: int
    tile: str
    cameras: list[str]
    cells: int  # cells the window mapped in the tile
    semantics: bool


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    write(tmp)
    os.replace(tmp, path)


def save_npz(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """`arrays` compressed into `path`, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)

    def write(tmp: Path) -> None:
        with open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    _atomic_write(path, write)


def save_json(path: Path, data: dict) -> None:
    """`data` as JSON into `path`, atomically."""
    path.parent.mkdir(parents=True, exist_ok=True)
    _atomic_write(path, lambda tmp: tmp.write_text(json.dumps(data, indent=1, default=str)))


@dataclass(frozen=True)
class TileStore:
    """The tile store under `root`."""

    root: Path

    def tile_folder(self, tile: TileId) -> Path:
        return self.root / "tiles" / str(tile)

    def write(self, tile: TileId, contribution: Contribution) -> ContributionInfo:
        folder = self.tile_folder(tile)
        arrays = {"height": contribution.height, "weight": contribution.weight}
        arrays |= {f"rgb_{c}": v for c, v in contribution.rgb.items()}
        if contribution.class_prob is not None:
            arrays["class_prob"] = contribution.class_prob
        save_npz(folder / f"{contribution.name}.npz", arrays)
        info = ContributionInfo(contribution.drive, contribution.window, str(tile), sorted(contribution.rgb),
                                int(np.isfinite(contribution.height).sum()), contribution.class_prob is not None)
        save_json(folder / f"{contribution.name}.json", asdict(info))
        return info

    def tiles(self) -> list[TileId]:
        """Every tile with at least one finished contribution."""
        folder = self.root / "tiles"
        if not folder.is_dir():
            return []
        return sorted(TileId.parse(p.name) for p in folder.iterdir() if p.is_dir() and any(p.glob("*.json")))

    def contributions(self, tile: TileId) -> list[ContributionInfo]:
        return [ContributionInfo(**json.loads(p.read_text())) for p in sorted(self.tile_folder(tile).glob("*.json"))]

    def read(self, tile: TileId, info: ContributionInfo) -> Contribution:
        with np.load(self.tile_folder(tile) / f"{info.drive}.w{info.window}.npz") as z:
            return Contribution(info.drive, info.window, z["height"], z["weight"],
                                z["class_prob"] if "class_prob" in z.files else None,
                                {c: z[f"rgb_{c}"] for c in info.cameras})

    def merged_path(self, tile: TileId) -> Path:
        return self.root / "merged" / f"{tile}.npz"
