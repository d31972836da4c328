"""The map's mesh on disk: PLY in the map's ENU frame (x east, y north, z up, as the rasters), GLB by the glTF
convention (+Y up, right-handed): X east, Y up, Z south, so standard viewers show the road lying flat."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

MESH_FILES = ("mesh.ply", "mesh.glb")
# ENU (east, north, up) -> glTF (X, Y, Z) = (east, up, -north): a rotation of -90 degrees about the east axis
ENU_TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def write_mesh_files(mesh: trimesh.Trimesh, out: Path) -> dict[str, Path]:
    """`mesh` (ENU vertices) as mesh.ply (ENU) and mesh.glb (its vertices rotated into glTF's Y-up frame)."""
    mesh.export(out / "mesh.ply")
    gltf = mesh.copy()
    gltf.vertices = mesh.vertices @ ENU_TO_GLTF.T  # a rotation: faces keep their winding, normals turn with them
    gltf.export(out / "mesh.glb")
    return {name: out / name for name in MESH_FILES}
