"""Mesh files (trimesh lives here): read segment meshes, write OBJ / GLB bodies."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from torchfit.errors import DataError, ModelError
from torchfit.io.files import write_atomic

__all__ = ["load_mesh_arrays", "save_mesh"]


def load_mesh_arrays(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a triangle mesh file (OBJ, PLY, STL, GLB, …).

    Returns:
        vertices (V, 3) float64 and faces (F, 3) int64, file order kept.

    Raises:
        ModelError: the file is missing, unreadable or not a triangle mesh.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ModelError(f"mesh file not found: {path}")
    try:
        mesh = trimesh.load(path, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for corrupt files
        raise ModelError(f"cannot read mesh {path}: {exc}") from exc
    vertices = np.asarray(mesh.vertices, dtype=np.float64)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or len(faces) == 0:
        raise ModelError(
            f"mesh {path}: expected a non-empty triangle mesh, got "
            f"{vertices.shape[0]} vertices and {len(faces)} faces"
        )
    return vertices, faces


def save_mesh(path: str | Path, vertices: np.ndarray, faces: np.ndarray) -> Path:
    """Write a triangle mesh atomically; the format follows the suffix (``.obj``, ``.glb``,
    ``.ply``, ``.stl``).

    Args:
        vertices: (V, 3) metres.
        faces: (F, 3) vertex indices.
    """
    import trimesh

    path = Path(path)
    if path.suffix.lower() not in {".obj", ".glb", ".ply", ".stl"}:
        raise DataError(f"save_mesh: unsupported mesh format {path.suffix!r} for {path}")
    mesh = trimesh.Trimesh(np.asarray(vertices), np.asarray(faces), process=False)
    return write_atomic(path, mesh.export(file_type=path.suffix.lower()[1:]))
