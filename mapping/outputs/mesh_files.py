"""The map's mesh on disk: PLY in the map's ENU frame (x east, y north, z up, as the rasters), GLB by the glTF
convention (+Y up, right-handed): X east, Y up, Z south, so standard viewers show the road lying flat."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

MESH_FILES = ("mesh.ply", "mesh.glb")
# ENU (east, north, up) -> glTF (X, Y, Z) = (east, up, -north): a rotation of -90 degrees about the east axis
ENU_TO_GLTF = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
GLTF_AXES = "metres; X east, Y up, Z south of the local ENU frame whose origin is origin_lat_lon_alt (WGS84)"


def write_mesh_files(mesh: trimesh.Trimesh, out: Path, origin_lat_lon_alt: list[float] | None) -> dict[str, Path]:
    """`mesh` (ENU vertices) as mesh.ply (ENU) and mesh.glb (its vertices rotated into glTF's Y-up frame, the
    frame's origin in the mesh's extras: `roadlog.origin_lat_lon_alt`)."""
    mesh.export(out / "mesh.ply")
    gltf = mesh.copy()
    gltf.vertices = mesh.vertices @ ENU_TO_GLTF.T  # a rotation: faces keep their winding, normals turn with them
    gltf.metadata["roadlog"] = {"origin_lat_lon_alt": origin_lat_lon_alt, "axes": GLTF_AXES}
    gltf.export(out / "mesh.glb")
    return {name: out / name for name in MESH_FILES}
