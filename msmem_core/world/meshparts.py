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
- **Checked.** A vertex that is not finite is refused, naming the file and the vertex. The pieces'
  volume is compared with the mesh's (a watertight mesh) or its convex hull's (any other), naming
  both volumes: pieces of a watertight mesh holding less than ``MIN_VOLUME_RATIO`` of it are refused;
  pieces of any other mesh holding less than ``MIN_HULL_RATIO`` of its hull, and pieces holding more
  than ``MAX_VOLUME_RATIO`` times the reference, are warned about. Cached pieces are checked the
  same way.
- **URDFs.** The first collision mesh (else the first visual mesh) with its ``scale`` and its
  ``<origin rpy xyz>``. Its ``filename`` must lie in the URDF's folder, or be
  ``package://NAME/...`` inside a declared package root (a folder named ``NAME``): absolute paths,
  ``file://`` paths outside the folder, ``..`` and symlinks that lead out are refused before the file
  is read, naming the URDF and the path.
- **Progress.** A decomposition still running after ``PROGRESS_AFTER_S`` says so on stderr, and
  says how long it took when done.
- **Cache.** Decomposing takes seconds to minutes, so the pieces are cached as JSON, keyed by the
  file's content, scale and settings: beside the mesh (``<mesh>.hulls-<key>.json``) when that
  folder is writable, else in ``$MSMEM_CACHE_DIR/meshes`` (default ``~/.cache/msmem/meshes``).
  Decompositions that ship with msmem (``shipped_cache_dir``) are found first, by the same key.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import sys
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from msmem_core.errors import UserError
from msmem_core.util.artifacts import atomic_text, cache_root
from msmem_core.world.geometry import pose_matrix

log = logging.getLogger(__name__)

CACHE_VERSION = 1
MESH_SUFFIXES = (".obj", ".stl", ".ply", ".off", ".glb", ".gltf")
MIN_VOLUME_RATIO = 0.5
"""Pieces of a watertight mesh holding less than this fraction of its volume are refused: they cover
the mesh, so they hold about as much or more."""
MIN_HULL_RATIO = 0.1
"""Pieces of any other mesh holding less than this fraction of its convex hull's volume are warned
about: the thin walls of an open container's surface may, the sliver left of a broken mesh does."""
MAX_VOLUME_RATIO = 2.0
"""Pieces holding more than this many times the reference volume are warned about (a thin-walled
closed mesh whose pieces fill its inside)."""
PROGRESS_AFTER_S = 3.0
"""A decomposition running longer than this says so on stderr."""
_WARNED: set[str] = set()


@dataclass(frozen=True)
class MeshReport:
    """How the pieces of a mesh were made: piece count, whether CoACD ran, the mesh's and the pieces'
    volume (m^3; the mesh's is NaN when it is not watertight) and where the cache is."""

    pieces: int
    decomposed: bool
    mesh_volume_m3: float
    pieces_volume_m3: float
    cache: Path
    hull_volume_m3: float = float("nan")
    """The mesh's convex hull's volume (the reference for a mesh that is not watertight)."""


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


@dataclass(frozen=True)
class UrdfMesh:
    """The mesh a URDF names for its geometry, where it lies and how the URDF places it."""

    urdf: Path
    mesh: Path
    scale: NDArray[np.float64]
    """The ``<mesh scale>`` (per axis)."""
    origin: NDArray[np.float64]
    """4x4: the ``<origin rpy xyz>`` of the collision (or visual) element, in the link frame."""


def rpy_matrix(rpy: Sequence[float] | NDArray[np.float64]) -> NDArray[np.float64]:
    """The rotation of a URDF ``rpy``: roll about x, then pitch about y, then yaw about z, all about the
    fixed axes (R = Rz(yaw) Ry(pitch) Rx(roll))."""
    r, p, y = (float(a) for a in rpy)
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), math.sin(y)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _numbers(urdf: Path, what: str, text: str | None, default: str) -> NDArray[np.float64]:
    try:
        v = np.array([float(x) for x in (text or default).split()], dtype=np.float64)
        v = np.broadcast_to(v, (3,)).copy()
    except ValueError:
        raise UserError(f"URDF {urdf}: {what} must be 3 numbers, got {text!r}") from None
    if not np.all(np.isfinite(v)):
        raise UserError(f"URDF {urdf}: {what} must be finite, got {text!r}")
    return v


def urdf_mesh_path(urdf: Path, name: str, package_roots: Sequence[str | Path] = ()) -> Path:
    """The file a URDF's ``<mesh filename>`` names, which must lie in the URDF's folder (a relative path,
    optionally ``file://``) or in a declared package root (``package://NAME/...``, the root being a
    folder named ``NAME``). Anything else (an absolute path, ``..`` or a symlink leading out, another
    package) is refused naming the URDF and the path; nothing is read."""
    where = f"URDF {urdf}: mesh filename {name!r}"
    if name.startswith("package://"):
        package, _, rest = name.removeprefix("package://").partition("/")
        roots = [Path(r).resolve() for r in package_roots if Path(r).name == package]
        if not roots:
            declared = ", ".join(str(r) for r in package_roots) or "none"
            raise UserError(f"{where}: package {package!r} is not a declared package root (mesh.package_roots, "
                            f"folders named after their package; declared: {declared})")
        base = roots[0]
        target = base / rest
    elif "://" in name and not name.startswith("file://"):
        raise UserError(f"{where}: only relative paths, file:// and package:// are read")
    else:
        rel = name.removeprefix("file://")
        if Path(rel).is_absolute():
            raise UserError(f"{where}: an absolute path; a URDF's meshes must lie in its folder {urdf.parent} "
                            "or in a declared package root (package://NAME/...)")
        base = urdf.parent.resolve()
        target = base / rel
    real = target.resolve()  # follows symlinks without reading
    if not real.is_relative_to(base):
        raise UserError(f"{where} leads to {real}, outside {base}; a URDF's meshes must lie in its folder or in a "
                        "declared package root")
    return real


def _urdf_mesh(path: Path, package_roots: Sequence[str | Path] = ()) -> UrdfMesh:
    """The first collision mesh of a URDF (else its first visual mesh), its scale and its origin."""
    try:
        root = ET.parse(path).getroot()
    except (ET.ParseError, OSError) as e:
        raise UserError(f"mesh file {path}: not a readable URDF ({e})") from e
    for tag in ("collision", "visual"):
        for el in root.iter(tag):
            mesh = el.find("./geometry/mesh")
            if mesh is not None and mesh.get("filename"):
                file = urdf_mesh_path(path, mesh.get("filename", ""), package_roots)
                scale = _numbers(path, f"<{tag}> mesh scale", mesh.get("scale"), "1 1 1")
                origin = el.find("origin")
                rpy = _numbers(path, f"<{tag}> origin rpy", None if origin is None else origin.get("rpy"), "0 0 0")
                xyz = _numbers(path, f"<{tag}> origin xyz", None if origin is None else origin.get("xyz"), "0 0 0")
                t = np.eye(4)
                t[:3, :3] = rpy_matrix(rpy)
                t[:3, 3] = xyz
                return UrdfMesh(path, file, scale, t)
    raise UserError(f"mesh file {path}: the URDF has no <collision> or <visual> mesh")


def _finite_vertices(p: Path, where: str) -> None:
    """Refuse a mesh file with a vertex that is not finite, naming it (read without processing, which
    would drop it silently)."""
    import trimesh

    try:
        raw = trimesh.load(p, force="mesh", process=False)
    except Exception as e:  # trimesh raises many kinds for a broken file
        raise UserError(f"{where}: cannot be read as a mesh ({type(e).__name__}: {e})") from e
    v = np.asarray(getattr(raw, "vertices", np.zeros((0, 3))))
    bad = np.flatnonzero(~np.isfinite(v).all(axis=1)) if v.ndim == 2 else np.zeros(0, dtype=np.int64)
    if len(bad):
        i = int(bad[0])
        more = f" ({len(bad)} such vertices)" if len(bad) > 1 else ""
        raise UserError(f"{where}: vertex {i} (counting from 0, of {len(v)}) is not finite: "
                        f"{v[i].tolist()}{more}")


def load_mesh(path: str | Path, scale: float | tuple[float, float, float] = 1.0,
              quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
              package_roots: Sequence[str | Path] = ()) -> Any:
    """The mesh as a ``trimesh.Trimesh`` in the object frame (module docstring): scaled (a URDF's mesh:
    by the URDF's scale, placed by its origin, then scaled by ``scale``), rotated by ``quat_xyzw``,
    then centred."""
    import trimesh

    p = resolve(path)
    if not p.is_file():
        raise UserError(f"mesh file {p} does not exist")
    s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,)).copy()
    where = f"mesh file {p}"
    placed = None
    if p.suffix.lower() == ".urdf":
        u = _urdf_mesh(p, package_roots)
        where = f"mesh file {u.mesh} (of URDF {p})"
        p = u.mesh
        if not p.is_file():
            raise UserError(f"{where} does not exist")
        if np.allclose(u.origin, np.eye(4)):
            s = s * u.scale
        else:
            placed = u
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise UserError(f"{where}: unknown format {p.suffix!r}; use one of {', '.join(MESH_SUFFIXES)} or .urdf")
    if np.any(s <= 0) or not np.all(np.isfinite(s)):
        raise UserError(f"{where}: scale must be positive and finite, got {s.tolist()}")
    _finite_vertices(p, where)
    try:
        mesh = trimesh.load(p, force="mesh", process=True)
    except Exception as e:  # trimesh raises many kinds for a broken file
        raise UserError(f"{where}: cannot be read as a mesh ({type(e).__name__}: {e})") from e
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"{where}: holds no triangles")
    if placed is not None:  # the URDF's scale in the mesh's frame, then its origin in the link's
        if np.any(placed.scale <= 0):
            raise UserError(f"{where}: the URDF's scale must be positive, got {placed.scale.tolist()}")
        mesh.apply_transform(np.diag([*placed.scale, 1.0]))
        mesh.apply_transform(placed.origin)
    mesh.apply_scale(s) if np.allclose(s, s[0]) else mesh.apply_transform(np.diag([*s, 1.0]))
    mesh.apply_transform(pose_matrix((0.0, 0.0, 0.0), quat_xyzw))
    lo, hi = mesh.bounds
    mesh.apply_translation([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return mesh


def _key(path: Path, scale: Any, settings: dict[str, Any], package_roots: Sequence[str | Path] = ()) -> str:
    h = hashlib.sha256()
    h.update(path.read_bytes())
    if path.suffix.lower() == ".urdf":  # the URDF names the mesh: its bytes count too
        u = _urdf_mesh(path, package_roots)  # refuses a mesh outside its roots before reading it
        if not u.mesh.is_file():
            raise UserError(f"mesh file {u.mesh} (of URDF {path}) does not exist")
        h.update(u.mesh.read_bytes())
        if not np.allclose(u.origin, np.eye(4)):  # pieces cached before origins were applied are not these
            h.update(np.round(u.origin, 9).tobytes())
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


def _check_volumes(where: str, pieces_m3: float, mesh_m3: float, hull_m3: float, cache: Path) -> None:
    """Refuse pieces holding far less than a watertight mesh; warn once about pieces holding far less
    than any other mesh's hull, or far more than the reference (``MIN_VOLUME_RATIO``, ``MIN_HULL_RATIO``,
    ``MAX_VOLUME_RATIO``)."""
    watertight = not math.isnan(mesh_m3)
    ref = mesh_m3 if watertight else hull_m3
    what = "the mesh" if watertight else "its convex hull (the mesh is not watertight)"
    if not ref > 0:
        raise UserError(f"{where}: {what} holds no volume ({ref:.3g} m^3); a flat or degenerate mesh cannot be an "
                        "object")
    ratio = pieces_m3 / ref
    said = (f"its convex pieces hold {pieces_m3:.3g} m^3 where {what} holds {ref:.3g} m^3 "
            f"(ratio {ratio:.2f})")
    if watertight and ratio < MIN_VOLUME_RATIO:
        raise UserError(f"{where}: {said}, below {MIN_VOLUME_RATIO}: the decomposition lost most of the object "
                        f"(cache {cache}); check the mesh for stray faces, or lower threshold")
    if str(cache) in _WARNED:
        return
    if not watertight and ratio < MIN_HULL_RATIO:
        _WARNED.add(str(cache))
        log.warning("%s: %s, below %s: the pieces are thin walls or a sliver; if the object is solid, close the "
                    "mesh's holes (a watertight mesh is checked against its own volume)", where, said, MIN_HULL_RATIO)
    elif ratio > MAX_VOLUME_RATIO:
        _WARNED.add(str(cache))
        log.warning("%s: %s, above %s: the pieces fill what the mesh leaves empty (a thin-walled mesh?); raise "
                    "max_hulls or lower threshold to follow it more closely", where, said, MAX_VOLUME_RATIO)


def _progress(where: str, triangles: int, max_hulls: int) -> tuple[threading.Timer, float]:
    """A timer that says on stderr, after ``PROGRESS_AFTER_S``, that the decomposition is under way."""
    def say() -> None:
        print(f"msmem: decomposing {where} ({triangles} triangles) into at most {max_hulls} convex pieces with "
              "CoACD; this can take minutes, the pieces are cached", file=sys.stderr, flush=True)

    timer = threading.Timer(PROGRESS_AFTER_S, say)
    timer.daemon = True
    timer.start()
    return timer, time.perf_counter()


def mesh_pieces(
    path: str | Path, scale: float | tuple[float, float, float] = 1.0, max_hulls: int = 16,
    threshold: float = 0.05, convex_ratio: float = 0.95,
    quat_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
    package_roots: Sequence[str | Path] = (),
) -> tuple[list[NDArray[np.float64]], MeshReport]:
    """Vertices ``[N_i, 3]`` of each convex piece of the mesh in the object frame (cached), and how
    they were made. ``package_roots``: folders a URDF's ``package://NAME/`` meshes may lie in."""
    import trimesh

    p = resolve(path).resolve()
    settings = {"max_hulls": max_hulls, "threshold": threshold, "convex_ratio": convex_ratio,
                "quat_xyzw": [float(q) for q in quat_xyzw]}
    if not p.is_file():
        raise UserError(f"mesh file {p} does not exist")
    where = f"mesh file {p}"
    key = _key(p, scale, settings, package_roots)
    cache = _cache_file(p, key)
    if cache.is_file():
        try:
            data = json.loads(cache.read_text())
            pieces = _in_object_frame([np.asarray(v, dtype=np.float64) for v in data["pieces"]])
            vol = data["mesh_volume_m3"]
            report = MeshReport(len(pieces), data["decomposed"], float("nan") if vol is None else vol,
                                data["pieces_volume_m3"], cache, data.get("hull_volume_m3", float("nan")))
        except (OSError, ValueError, KeyError, TypeError):
            pass  # a broken cache file is made again
        else:
            unchecked = "hull_volume_m3" not in data  # no hull volume recorded: check the mesh as a new one
            if unchecked:
                mesh = load_mesh(p, scale, quat_xyzw, package_roots)
                report = MeshReport(report.pieces, report.decomposed, report.mesh_volume_m3,
                                    report.pieces_volume_m3, cache, float(mesh.convex_hull.volume))
            _check_volumes(where, report.pieces_volume_m3, report.mesh_volume_m3, report.hull_volume_m3, cache)
            if unchecked and cache.parent != shipped_cache_dir():
                with contextlib.suppress(OSError):  # checked once: the record says so from now on
                    atomic_text(json.dumps({**data, "hull_volume_m3": report.hull_volume_m3}), cache)
            return pieces, report
    mesh = load_mesh(p, scale, quat_xyzw, package_roots)
    hull = mesh.convex_hull
    volume = abs(float(mesh.volume)) if mesh.is_watertight else float("nan")  # inside out: as much
    decomposed = not (mesh.is_watertight and volume >= convex_ratio * float(hull.volume))
    if decomposed:
        import coacd

        coacd.set_log_level("error")
        timer, t0 = _progress(where, len(mesh.faces), max_hulls)
        try:
            parts = coacd.run_coacd(coacd.Mesh(np.asarray(mesh.vertices), np.asarray(mesh.faces)),
                                    threshold=threshold, max_convex_hull=max_hulls, seed=0)
        finally:
            timer.cancel()
        seconds = time.perf_counter() - t0
        if seconds >= PROGRESS_AFTER_S:
            print(f"msmem: decomposed {where} into {len(parts)} convex pieces in {seconds:.1f} s (cached: {cache})",
                  file=sys.stderr, flush=True)
        pieces = [np.asarray(trimesh.convex.convex_hull(np.asarray(v)).vertices, dtype=np.float64) for v, _ in parts]
    else:
        pieces = [np.asarray(hull.vertices, dtype=np.float64)]
    pieces = [np.round(v, 6) for v in pieces if len(v) >= 4]
    pieces_volume = float(sum(trimesh.convex.convex_hull(v).volume for v in pieces))
    report = MeshReport(len(pieces), decomposed, volume, pieces_volume, cache, float(hull.volume))
    _check_volumes(where, pieces_volume, volume, report.hull_volume_m3, cache)
    pieces = _in_object_frame(pieces)
    cache.parent.mkdir(parents=True, exist_ok=True)
    record = {"source": str(p), "key": key, "decomposed": decomposed,
              "mesh_volume_m3": None if np.isnan(volume) else volume, "pieces_volume_m3": pieces_volume,
              "hull_volume_m3": report.hull_volume_m3, "pieces": [v.tolist() for v in pieces]}
    atomic_text(json.dumps(record), cache)
    return pieces, report
