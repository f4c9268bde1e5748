"""Mesh objects as convex parts: a mesh file (OBJ, STL, PLY, or a URDF's collision mesh) becomes the
convex pieces every backend, ground truth and the scene tools share (``Part(kind="convex")``).

- **Frame.** The mesh is scaled, then moved so that its bounding box is centred on the object's
  origin in x and y and its lowest point is at z = 0 (the object's support), as the built-in classes.
- **Pieces.** A mesh that is nearly convex (watertight, volume at least ``convex_ratio`` of its
  hull's) is one piece: its hull. Any other mesh is split by CoACD (collision-aware approximate convex
  decomposition, the ``coacd`` package) with the given concavity ``threshold`` and at most
  ``max_hulls`` pieces, seeded so the result is the same on every run.
- **Agreement.** Physics, the cameras, ground truth and the antipodal grasps all use these pieces, so
  all agree on the geometry. The pieces approximate the mesh; ``MeshReport`` says by how much (their
  volume against the mesh's).
- **Cache.** Decomposing takes seconds to minutes, so the pieces are cached as JSON, keyed by the
  file's content, scale and settings: beside the mesh (``<mesh>.hulls-<key>.json``) when that
  folder is writable, else in ``$MSMEM_CACHE_DIR/meshes`` (default ``~/.cache/msmem/meshes``).
  Decompositions that ship with msmem (``shipped_cache_dir``) are found first, by the same key.
"""

from __future__ import annotations

import hashlib
import json
import os
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.util.artifacts import atomic_text, cache_root
from msmem_core.world.geometry import pose_matrix

CACHE_VERSION = 1
MESH_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf")


@dataclass(frozen=True)
class MeshReport:
    """How the pieces of a mesh were made: piece count, whether CoACD ran, the mesh's and the pieces'
    volume (m^3; the mesh's is NaN when it is not watertight) and where the cache is."""

    pieces: int
    decomposed: bool
    mesh_volume_m3: float
    pieces_volume_m3: float
    cache: Path


PACKAGE_PREFIX = "pybullet_data:"
"""A mesh path starting with this is inside the ``pybullet_data`` package (e.g. ``pybullet_data:duck.obj``),
wherever it is installed."""


def resolve(path: str | Path) -> Path:
    """The file a mesh path names (``PACKAGE_PREFIX`` paths in the installed ``pybullet_data``)."""
    s = str(path)
    if s.startswith(PACKAGE_PREFIX):
        import pybullet_data

        return Path(pybullet_data.getDataPath()) / s.removeprefix(PACKAGE_PREFIX)
    return Path(path)


def cache_dir() -> Path:
    """``$MSMEM_CACHE_DIR/meshes`` or ``~/.cache/msmem/meshes``."""
    return cache_root("meshes")


def _urdf_mesh(path: Path) -> tuple[Path, NDArray[np.float64]]:
    """The first collision mesh of a URDF (else its first visual mesh) and its scale."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise UserError(f"mesh file {path}: not a readable URDF ({e})") from e
    for tag in ("collision", "visual"):
        for el in root.iter(tag):
            mesh = el.find("./geometry/mesh")
            if mesh is not None and mesh.get("filename"):
                name = mesh.get("filename", "").removeprefix("file://")
                scale = np.array([float(v) for v in (mesh.get("scale") or "1 1 1").split()], dtype=np.float64)
                return (path.parent / name).resolve(), np.broadcast_to(scale, (3,)).copy()
    raise UserError(f"mesh file {path}: the URDF has no <collision> or <visual> mesh")


def load_mesh(path: str | Path, scale: float | tuple[float, float, float] = 1.0,
              quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)) -> Any:
    """The mesh as a ``trimesh.Trimesh`` in the object frame (module docstring): scaled, rotated by
    ``quat_xyzw``, then centred."""
    import trimesh

    p = resolve(path)
    if not p.is_file():
        raise UserError(f"mesh file {p} does not exist")
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)).copy()
    if p.suffix.lower() == ".urdf":
        p, urdf_scale = _urdf_mesh(p)
        s = s * urdf_scale
        if not p.is_file():
            raise UserError(f"mesh file {path}: its mesh {p} does not exist")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise UserError(f"mesh file {p}: unknown format {p.suffix!r}; use one of {', '.join(MESH_SUFFIXES)} or .urdf")
    try:
        mesh = trimesh.load(p, force="mesh", process=True)
    except Exception as e:  # trimesh raises many kinds for a broken file
        raise UserError(f"mesh file {p}: cannot be read as a mesh ({type(e).__name__}: {e})") from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"mesh file {p}: holds no triangles")
    if np.any(s <= 0) or not np.all(np.isfinite(s)):
        raise UserError(f"mesh file {p}: scale must be positive and finite, got {s.tolist()}")
    mesh.apply_scale(s) if np.allclose(s, s[0]) else mesh.apply_transform(np.diag([*s, 1.0]))
    mesh.apply_transform(pose_matrix((0.0, 0.0, 0.0), quat_xyzw))
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return mesh


def _key(path: Path, scale: Any, settings: dict[str, Any]) -> str:
    h = hashlib.sha256()
    h.update(path.read_bytes())
    if path.suffix.lower() == ".urdf":  # the URDF names the mesh: its bytes count too
        h.update(_urdf_mesh(path)[0].read_bytes())
    h.update(json.dumps({"v": CACHE_VERSION, "scale": np.asarray(scale, dtype=float).tolist(), **settings},
                        sort_keys=True).encode())
    return h.hexdigest()[:16]


def shipped_cache_dir() -> Path:
    """Decompositions that ship with msmem (``msmem_core/world/hulls``: the ``mesh25`` suite's meshes),
    found by the same content key, so no suite needs CoACD at run time."""
    return Path(__file__).with_name("hulls")


def _cache_file(path: Path, key: str) -> Path:
    shipped = shipped_cache_dir() / f"{path.name}.hulls-{key}.json"
    if shipped.is_file():
        return shipped
    beside = path.with_name(f"{path.name}.hulls-{key}.json")
    if beside.exists() or os.access(path.parent, os.W_OK):
        return beside
    return cache_dir() / f"{path.stem}.hulls-{key}.json"


def _in_object_frame(pieces: list[NDArray[np.float64]]) -> list[NDArray[np.float64]]:
    """The pieces moved as the mesh was (bounding box centred in x and y, lowest point at z = 0): a
    decomposition's hulls may reach a little past the mesh (CoACD's remeshing), and an object must
    not reach into the board it stands on."""
    lo = np.min([v.min(axis=0) for v in pieces], axis=0)
    hi = np.max([v.max(axis=0) for v in pieces], axis=0)
    shift = np.array([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return [np.round(v + shift, 6) for v in pieces]


def mesh_pieces(
    path: str | Path, scale: float | tuple[float, float, float] = 1.0, max_hulls: int = 16,
    threshold: float = 0.05, convex_ratio: float = 0.95,
    quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
) -> tuple[list[NDArray[np.float64]], MeshReport]:
    """Vertices ``[N_i, 3]`` of each convex piece of the mesh in the object frame (cached), and how
    they were made."""
    import trimesh

    p = resolve(path).resolve()
    settings = {"max_hulls": max_hulls, "threshold": threshold, "convex_ratio": convex_ratio,
                "quat_xyzw": [float(q) for q in quat_xyzw]}
    if not p.is_file():
        raise UserError(f"mesh file {p} does not exist")
    key = _key(p, scale, settings)
    cache = _cache_file(p, key)
    if cache.is_file():
        try:
            data = json.loads(cache.read_text())
            pieces = _in_object_frame([np.asarray(v, dtype=np.float64) for v in data["pieces"]])
            vol = data["mesh_volume_m3"]
            return pieces, MeshReport(len(pieces), data["decomposed"], float("nan") if vol is None else vol,
                                      data["pieces_volume_m3"], cache)
        except (OSError, ValueError, KeyError):
            pass  # a broken cache file is made again
    mesh = load_mesh(p, scale, quat_xyzw)
    hull = mesh.convex_hull
    volume = float(mesh.volume) if mesh.is_watertight else float("nan")
    decomposed = not (mesh.is_watertight and volume >= convex_ratio * float(hull.volume))
    if decomposed:
        import coacd

        coacd.set_log_level("error")
        parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)), threshold=threshold,
                                max_convex_hull=max_hulls, seed=0)
        pieces = [np.asarray(trimesh.convex.convex_hull(np.asarray(v)).vertices, dtype=np.float64) for v, _ in parts]
    else:
        pieces = [np.asarray(hull.vertices, dtype=np.float64)]
    pieces = [np.round(v, 6) for v in pieces if len(v) >= 4]
    pieces_volume = float(sum(trimesh.convex.convex_hull(v).volume for v in pieces))
    report = MeshReport(len(pieces), decomposed, volume, pieces_volume, cache)
    pieces = _in_object_frame(pieces)
    cache.parent.mkdir(parents=True, exist_ok=True)
    record = {"source": str(p), "key": key, "decomposed": decomposed,
              "mesh_volume_m3": None if np.isnan(volume) else volume, "pieces_volume_m3": pieces_volume,
              "pieces": [v.tolist() for v in pieces]}
    atomic_text(json.dumps(record), cache)
    return pieces, report
