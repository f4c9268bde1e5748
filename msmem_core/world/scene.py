"""Scene descriptions: the shelf, the object catalogue and ``SceneSpec`` (stored as JSON).

Every object class is a union of convex parts (boxes and cylinders in the object frame, whose
origin is the centre of the object's footprint on its support). Backends build compound collision
shapes from the parts; ground truth voxelises the same parts, so all agree on the geometry.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from functools import cache
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import (
    AfterValidator,
    BaseModel,
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from msmem_core.errors import UserError
from msmem_core.util.validation import FROZEN_MODEL_CONFIG, Bool, Int, error_lines, load_json
from msmem_core.world.geometry import pose_matrix


def _rotation(q: tuple[float, float, float, float]) -> tuple[float, float, float, float]:
    if math.hypot(*q) < 1e-6:
        raise ValueError(f"quaternion {q} has no rotation: its norm is 0 (identity: [0, 0, 0, 1])")
    return q


Quaternion = Annotated[tuple[float, float, float, float], AfterValidator(_rotation)]
"""A rotation as (x, y, z, w); any non-zero length (it is normalised where used)."""


class Part(BaseModel):
    """One convex primitive of an object, in the object frame: a box, a cylinder, or the convex hull
    of ``vertices_m`` (``convex``: the pieces of a mesh's convex decomposition, ``world.meshparts``)."""

    model_config = FROZEN_MODEL_CONFIG

    kind: Literal["box", "cylinder", "convex"]
    size_m: tuple[float, ...] = ()
    """box: full extents (x, y, z); cylinder: (radius, height) along the part's z; convex: unused."""
    vertices_m: tuple[tuple[float, float, float], ...] = ()
    """convex: points whose hull is the part, in the part's frame (at least 4, not coplanar)."""
    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    quat_xyzw: Quaternion = (0.0, 0.0, 0.0, 1.0)

    @model_validator(mode="after")
    def _shape(self) -> Part:
        want = {"box": 3, "cylinder": 2, "convex": 0}[self.kind]
        if len(self.size_m) != want or any(v <= 0 for v in self.size_m):
            raise ValueError(f"a {self.kind} part needs size_m of {want} positive values" if want else
                             "a convex part takes vertices_m, not size_m")
        if self.kind == "convex":
            v = np.asarray(self.vertices_m, dtype=np.float64).reshape(-1, 3)
            if len(v) < 4 or np.linalg.matrix_rank(v[1:] - v[0], tol=1e-6) < 3:
                raise ValueError("a convex part needs at least 4 vertices_m that are not coplanar")
        elif self.vertices_m:
            raise ValueError(f"a {self.kind} part takes size_m, not vertices_m")
        return self

    @property
    def half_height_m(self) -> float:
        if self.kind == "convex":
            z = np.asarray(self.vertices_m)[:, 2]
            return float(z.max() - z.min()) / 2
        return self.size_m[2] / 2 if self.kind == "box" else self.size_m[1] / 2

    def volume_and_centroid(self) -> tuple[float, NDArray[np.float64]]:
        """Volume (m^3) and centroid in the object frame."""
        if self.kind == "box":
            return float(np.prod(self.size_m)), np.asarray(self.position_m, dtype=np.float64)
        if self.kind == "cylinder":
            return math.pi * self.size_m[0] ** 2 * self.size_m[1], np.asarray(self.position_m, dtype=np.float64)
        from scipy.spatial import ConvexHull

        v = np.asarray(self.vertices_m, dtype=np.float64)
        hull = ConvexHull(v)
        c = v[hull.vertices].mean(axis=0)  # an interior point: split the hull into tetrahedra from it
        tri = v[hull.simplices]
        vols = np.abs(np.einsum("ij,ij->i", tri[:, 0] - c, np.cross(tri[:, 1] - c, tri[:, 2] - c))) / 6
        local = ((tri.sum(axis=1) + c) / 4 * vols[:, None]).sum(axis=0) / vols.sum()
        return float(vols.sum()), pose_matrix(self.position_m, self.quat_xyzw)[:3, :3] @ local + self.position_m

    def footprint_radius_m(self) -> float:
        """Largest horizontal distance of the part from the object's origin."""
        if self.kind == "convex":
            w = np.asarray(self.vertices_m) @ pose_matrix((0, 0, 0), self.quat_xyzw)[:3, :3].T + self.position_m
            return float(np.hypot(w[:, 0], w[:, 1]).max())
        ext = self.size_m[0] if self.kind == "cylinder" else 0.5 * float(np.hypot(self.size_m[0], self.size_m[1]))
        return float(np.hypot(self.position_m[0], self.position_m[1])) + ext


class ObjectClass(BaseModel):
    """A semantic class with YCB-like size, mass and geometry."""

    model_config = FROZEN_MODEL_CONFIG

    name: str
    class_id: Int = Field(ge=1)
    parts: tuple[Part, ...]
    mass_kg: float = Field(gt=0.0)
    confusable_with: str | None = None
    """Class the structured segmentation noise may report instead of this one."""
    confusable_id: Int | None = None
    """Its class id (filled in with the registry the class belongs to)."""
    color_rgb: tuple[float, float, float] | None = None
    """Report colour (0..1); None: the report's palette colour for the class id."""

    @property
    def footprint_radius_m(self) -> float:
        return max((p.footprint_radius_m() for p in self.parts), default=0.0)


def parts_centroid(parts: Sequence[Part]) -> NDArray[np.float64]:
    """Volume-weighted centroid of the parts (overlaps counted twice; good enough for a mass centre).

    The backends put an object's mass centre here."""
    vc = [q.volume_and_centroid() for q in parts]
    vols = np.array([v for v, _ in vc])
    centres = np.array([c for _, c in vc], dtype=np.float64)
    return (vols[:, None] * centres).sum(axis=0) / vols.sum()


def _box(x: float, y: float, z: float, at: tuple[float, float, float] | None = None) -> Part:
    return Part(kind="box", size_m=(x, y, z), position_m=at or (0.0, 0.0, z / 2))


def _cyl(r: float, h: float, at: tuple[float, float, float] | None = None) -> Part:
    return Part(kind="cylinder", size_m=(r, h), position_m=at or (0.0, 0.0, h / 2))


def _ring(r_out: float, wall: float, h: float, z0: float, n: int = 10) -> list[Part]:
    """A thin-walled open cylinder as n boxes (non-convex containers: mug, bowl)."""
    parts = []
    chord = 2 * r_out * np.sin(np.pi / n) * 1.05
    for i in range(n):
        a = 2 * np.pi * i / n
        rc = r_out - wall / 2
        q = (0.0, 0.0, float(np.sin(a / 2)), float(np.cos(a / 2)))
        parts.append(
            Part(kind="box", size_m=(wall, chord, h), position_m=(rc * np.cos(a), rc * np.sin(a), z0 + h / 2),
                 quat_xyzw=q)
        )
    return parts


def _catalogue() -> tuple[ObjectClass, ...]:
    mug = [_cyl(0.040, 0.008), *_ring(0.040, 0.006, 0.080, 0.008)]
    mug += [_box(0.030, 0.012, 0.010, (0.052, 0.0, 0.070)), _box(0.010, 0.012, 0.050, (0.064, 0.0, 0.045)),
            _box(0.030, 0.012, 0.010, (0.052, 0.0, 0.020))]
    bowl = [_cyl(0.050, 0.010), *_ring(0.080, 0.008, 0.045, 0.010, n=12)]
    classes = [
        ("cracker_box", [_box(0.160, 0.060, 0.210)], 0.41, "sugar_box"),
        ("sugar_box", [_box(0.090, 0.040, 0.175)], 0.51, "cracker_box"),
        ("master_chef_can", [_cyl(0.051, 0.140)], 0.41, "tomato_soup_can"),
        ("tomato_soup_can", [_cyl(0.033, 0.101)], 0.35, "master_chef_can"),
        ("mustard_bottle", [_box(0.095, 0.058, 0.150), _cyl(0.015, 0.040, (0.02, 0.0, 0.170))], 0.60,
         "bleach_cleanser"),
        ("tuna_fish_can", [_cyl(0.043, 0.033)], 0.17, "potted_meat_can"),
        ("pudding_box", [_box(0.110, 0.089, 0.035)], 0.19, "gelatin_box"),
        ("gelatin_box", [_box(0.085, 0.073, 0.028)], 0.10, "pudding_box"),
        ("potted_meat_can", [_box(0.101, 0.051, 0.083)], 0.37, "tuna_fish_can"),
        ("mug", mug, 0.12, "bowl"),
        ("bleach_cleanser", [_box(0.100, 0.065, 0.200), _cyl(0.018, 0.040, (0.025, 0.0, 0.220)),
                             _box(0.010, 0.030, 0.060, (-0.030, 0.0, 0.230))], 1.13, "mustard_bottle"),
        ("bowl", bowl, 0.15, "mug"),
        ("foam_brick", [_box(0.075, 0.050, 0.050)], 0.03, "wood_block"),
        ("wood_block", [_box(0.085, 0.085, 0.200)], 0.73, "foam_brick"),
    ]
    ids = {n: i + 1 for i, (n, *_) in enumerate(classes)}
    return tuple(
        ObjectClass(name=n, class_id=i + 1, parts=tuple(p), mass_kg=m, confusable_with=c, confusable_id=ids[c])
        for i, (n, p, m, c) in enumerate(classes)
    )


OBJECT_CLASSES: tuple[ObjectClass, ...] = _catalogue()
CLASS_NAMES: tuple[str, ...] = ("background", *(c.name for c in OBJECT_CLASSES))
NUM_CLASSES = len(CLASS_NAMES)  # 15: background + 14 object classes
BACKGROUND = 0


@cache
def object_class(name: str) -> ObjectClass:
    """A built-in class by name (a scene's own classes: ``SceneSpec.object_class``)."""
    for c in OBJECT_CLASSES:
        if c.name == name:
            return c
    raise UserError(f"unknown object class {name!r}; known: {', '.join(c.name for c in OBJECT_CLASSES)}")


def model_classes(recorded: Sequence[str] | None, num_classes: int) -> tuple[str, ...] | None:
    """The classes a learned model was trained on: those its sidecar records, else (weights from
    before class lists were recorded) the built-ins when the count matches them, else None."""
    if recorded:
        return tuple(recorded)
    return CLASS_NAMES if num_classes == NUM_CLASSES else None


def class_mismatch(classes: Sequence[str], scene: tuple[str, ...], trained: Sequence[str] | None = None) -> str:
    """'' when a model that takes ``classes`` (background first) fits a scene with classes ``scene``, else
    what differs, naming the classes at fault and those the model knows. ``trained``: the classes its
    weights know when ``classes`` are those of its class map (the scene classes it maps onto them)."""
    if tuple(classes) == scene:
        return ""
    objects = scene[1:]
    if trained is not None:
        extra = [c for c in classes[1:] if c not in objects]
        unmapped = [c for c in objects if c not in classes]
        why = [f"its class_map maps {', '.join(extra)}, which the scene does not have"] if extra else []
        why += [f"it leaves {', '.join(unmapped)} unmapped"] if unmapped else []
        why = why or [f"its class_map lists the scene's classes in another order than the scene ({', '.join(objects)})"]
        return "; ".join(why) + f"; the weights know {counted_classes(trained)}"
    missing = [c for c in objects if c not in classes]
    if missing:
        return f"it does not know {', '.join(missing)}; it knows {counted_classes(classes)}"
    return f"it knows {counted_classes(classes)}, in this order; the scene has {', '.join(objects)}"


def counted_classes(classes: Sequence[str]) -> str:
    """The object classes of ``classes`` (background first), counted and named."""
    return f"{len(classes) - 1} object classes: {', '.join(classes[1:])}"


ClassName = Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]*$", max_length=64)]


class MeshSpec(BaseModel):
    """A mesh file as an object's geometry (``world.meshparts``): OBJ, STL, PLY, or a URDF whose first
    collision mesh (with its scale and origin) is used."""

    model_config = FROZEN_MODEL_CONFIG

    file: str
    """Relative paths in a scene file are relative to that file; ``pybullet_data:duck.obj`` is a file
    of the installed ``pybullet_data`` package."""
    scale: float | tuple[float, float, float] = 1.0
    """Metres per mesh unit (one factor, or one per axis)."""
    quat_xyzw: Quaternion = (0.0, 0.0, 0.0, 1.0)
    """Rotation of the mesh into the object frame (z up), applied after scaling: a y-up mesh standing
    upright takes (0.7071, 0, 0, 0.7071)."""
    max_hulls: Int = Field(16, ge=1, le=64)
    """At most this many convex pieces (CoACD)."""
    threshold: float = Field(0.05, gt=0.0, le=1.0)
    """CoACD's concavity threshold: lower follows the mesh more closely, with more pieces."""
    package_roots: tuple[str, ...] = ()
    """A URDF's meshes lie in its folder; ``package://NAME/...`` ones in the folder of these named
    ``NAME`` (relative paths in a scene file are relative to that file). Nothing else is read."""


class ClassSpec(BaseModel):
    """A class a scene declares beside the built-ins (docs/how-to/scenes.md): its name, its geometry (convex
    ``parts`` as the built-ins, or a ``mesh``), its mass, and optionally the class segmentation noise
    confuses it with and its colour in reports."""

    model_config = FROZEN_MODEL_CONFIG

    name: ClassName
    parts: tuple[Part, ...] = ()
    mesh: MeshSpec | None = None
    mass_kg: float = Field(0.2, gt=0.0, le=50.0)
    confusable_with: str | None = None
    color_rgb: tuple[float, float, float] | None = None
    """Report colour (0..1 per channel); None: a colour from the report's palette."""

    @model_validator(mode="after")
    def _one_geometry(self) -> ClassSpec:
        if bool(self.parts) == (self.mesh is not None):
            raise ValueError(f"class {self.name!r} needs either parts or a mesh")
        return self

    def geometry(self) -> tuple[Part, ...]:
        """The class's convex parts: its own, or its mesh's pieces (decomposed once, then cached)."""
        if self.mesh is None:
            return self.parts
        from msmem_core.world.meshparts import resolve

        m = self.mesh
        try:  # a changed file (size or time) is read again
            stat = resolve(m.file).stat()
            stamp = (stat.st_size, stat.st_mtime_ns)
        except (OSError, UserError):
            return _mesh_parts(m, None)  # mesh_pieces names the file at fault
        return _mesh_parts(m, stamp)


@cache
def _mesh_parts(mesh: MeshSpec, stamp: tuple[int, int] | None) -> tuple[Part, ...]:
    """A mesh's convex pieces as parts, once per mesh settings and file version: every scene that
    declares the class (a suite's 25 files) would otherwise read and hash the mesh and its cache again."""
    from msmem_core.world.meshparts import mesh_pieces

    pieces, _ = mesh_pieces(mesh.file, mesh.scale, mesh.max_hulls, mesh.threshold, quat_xyzw=mesh.quat_xyzw,
                            package_roots=mesh.package_roots)
    return tuple(Part(kind="convex", vertices_m=tuple(map(tuple, v))) for v in pieces)


class ShelfSpec(BaseModel):
    """Open-front shelf. Interior: x in [-w/2, w/2], y in [0, depth] (front at y = 0), z in [0, h]."""

    model_config = FROZEN_MODEL_CONFIG

    width_m: float = Field(0.76, gt=0.1, le=3.0)
    depth_m: float = Field(0.38, gt=0.1, le=2.0)
    height_m: float = Field(0.28, gt=0.05, le=2.0)
    wall_m: float = Field(0.02, gt=0.0, le=0.2)
    friction: float = Field(0.5, ge=0.0)

    @property
    def interior_lower(self) -> NDArray[np.float64]:
        return np.array([-self.width_m / 2, 0.0, 0.0])

    @property
    def interior_upper(self) -> NDArray[np.float64]:
        return np.array([self.width_m / 2, self.depth_m, self.height_m])

    @property
    def interior_box(self) -> tuple[float, float, float, float, float, float]:
        """The interior as (x_lo, y_lo, z_lo, x_hi, y_hi, z_hi)."""
        lo, hi = self.interior_lower, self.interior_upper
        return (float(lo[0]), float(lo[1]), float(lo[2]), float(hi[0]), float(hi[1]), float(hi[2]))

    def boards(self) -> list[tuple[NDArray[np.float64], NDArray[np.float64]]]:
        """(centre, half-extents) of the bottom, top, left, right and back boards."""
        w, d, h, t = self.width_m, self.depth_m, self.height_m, self.wall_m
        return [
            (np.array([0.0, d / 2, -t / 2]), np.array([w / 2 + t, d / 2, t / 2])),
            (np.array([0.0, d / 2, h + t / 2]), np.array([w / 2 + t, d / 2, t / 2])),
            (np.array([-w / 2 - t / 2, d / 2, h / 2]), np.array([t / 2, d / 2, h / 2 + t])),
            (np.array([w / 2 + t / 2, d / 2, h / 2]), np.array([t / 2, d / 2, h / 2 + t])),
            (np.array([0.0, d + t / 2, h / 2]), np.array([w / 2 + t, t / 2, h / 2 + t])),
        ]


class ObjectSpec(BaseModel):
    """One object instance: its class and its pose (object frame origin = footprint centre)."""

    model_config = FROZEN_MODEL_CONFIG

    id: Int = Field(ge=0)
    class_name: str
    """A built-in class, or one the scene declares in ``classes`` (checked by ``SceneSpec``)."""
    position_m: tuple[float, float, float]
    quat_xyzw: Quaternion = (0.0, 0.0, 0.0, 1.0)
    _class: ObjectClass | None = PrivateAttr(default=None)
    """The class as the scene that holds this object resolved it (its own classes included)."""

    @property
    def object_class(self) -> ObjectClass:
        return self._class if self._class is not None else object_class(self.class_name)

    @property
    def class_id(self) -> int:
        return self.object_class.class_id

    def pose(self) -> NDArray[np.float64]:
        return pose_matrix(self.position_m, self.quat_xyzw)


def relative_mesh_files(classes: Any, folder: Path) -> None:
    """In place: the relative mesh paths (and package roots) of raw class declarations (a list of
    mappings, as read from a file in ``folder``) made absolute against ``folder``; ``pybullet_data:...``
    paths stay."""
    for c in classes if isinstance(classes, list) else []:
        mesh = c.get("mesh") if isinstance(c, dict) else None
        if not isinstance(mesh, dict):
            continue
        file = mesh.get("file")
        if isinstance(file, str) and not Path(file).is_absolute() and ":" not in file:
            mesh["file"] = str((folder / file).resolve())
        roots = mesh.get("package_roots")
        if isinstance(roots, list):
            mesh["package_roots"] = [str((folder / r).resolve()) if isinstance(r, str) else r for r in roots]


class SceneSpec(BaseModel):
    """A shelf with objects; what ``Simulator.reset`` builds. Serialised as JSON."""

    model_config = FROZEN_MODEL_CONFIG

    name: str = "scene"
    seed: Int | None = None
    shelf: ShelfSpec = ShelfSpec()
    builtin_classes: Bool = True
    """The built-in classes are part of this scene's registry (False: only ``classes``, numbered from
    1, so the belief holds no class that cannot occur)."""
    classes: tuple[ClassSpec, ...] = ()
    """Classes beyond the built-ins, numbered after them in this order (ids 15, 16, ...)."""
    objects: tuple[ObjectSpec, ...] = ()
    occupancy_fraction: float | None = None
    """Fraction of the shelf floor covered by object footprints (recorded by the generator)."""
    hidden_objects: Int | None = None
    """Objects hidden from all viewpoints at the start (recorded by the hardness check)."""

    @field_validator("objects")
    @classmethod
    def _unique_ids(cls, v: tuple[ObjectSpec, ...]) -> tuple[ObjectSpec, ...]:
        ids = [o.id for o in v]
        if len(set(ids)) != len(ids):
            raise ValueError("object ids must be unique")
        return v

    @model_validator(mode="after")
    def _resolve_classes(self, info: ValidationInfo) -> SceneSpec:
        """Number the scene's classes after the built-ins and give every object its class; refuse
        unknown or duplicate names, naming the field. Classes that plugins offer (validation context
        ``offered_classes``: name -> ``ClassSpec``) are declared after the scene's own when an object
        names one the scene does not know."""
        offered: dict[str, ClassSpec] = (info.context or {}).get("offered_classes") or {}
        if offered:
            own = {c.name for c in self.classes} | ({c.name for c in OBJECT_CLASSES} if self.builtin_classes else set())
            used = [o.class_name for o in self.objects if o.class_name not in own and o.class_name in offered]
            extra = tuple(offered[n] for n in dict.fromkeys(used))
            if extra:
                object.__setattr__(self, "classes", self.classes + extra)
        if not self.builtin_classes and not self.classes:
            raise ValueError("classes: builtin_classes is false, so at least one class must be declared")
        known: dict[str, ObjectClass] = {c.name: c for c in OBJECT_CLASSES} if self.builtin_classes else {}
        builtin = {c.name for c in OBJECT_CLASSES}
        for i, c in enumerate(self.classes):
            if c.name in known or c.name in builtin:
                what = "a built-in class" if c.name in builtin else "declared twice"
                raise ValueError(f"classes.{i}.name: {c.name!r} is {what}")
            try:
                parts = c.geometry()
            except UserError as e:
                raise ValueError(f"classes.{i}.mesh: {e} (class {c.name!r})") from None
            known[c.name] = ObjectClass(name=c.name, class_id=len(known) + 1, parts=parts, mass_kg=c.mass_kg,
                                        confusable_with=c.confusable_with, color_rgb=c.color_rgb)
        for i, c in enumerate(self.classes):
            if c.confusable_with is not None:
                if c.confusable_with not in known:
                    raise ValueError(f"classes.{i}.confusable_with: unknown class {c.confusable_with!r}")
                known[c.name] = known[c.name].model_copy(update={"confusable_id": known[c.confusable_with].class_id})
        objects = []
        for i, o in enumerate(self.objects):
            if o.class_name not in known:
                raise ValueError(f"objects.{i}.class_name: unknown object class {o.class_name!r}; known: "
                                 f"{', '.join(known)} (declare a new one in the scene's classes, or install a "
                                 "plugin that declares it)")
            o = o.model_copy()
            o._class = known[o.class_name]
            objects.append(o)
        object.__setattr__(self, "objects", tuple(objects))  # the copies that know their class
        self._registry = tuple(known.values())
        return self

    _registry: tuple[ObjectClass, ...] = PrivateAttr(default=OBJECT_CLASSES)

    @property
    def object_classes(self) -> tuple[ObjectClass, ...]:
        """The built-in classes and the scene's own, in class-id order (ids 1, 2, ...)."""
        return self._registry

    @property
    def class_names(self) -> tuple[str, ...]:
        """``background`` and every object class, indexed by class id."""
        return ("background", *(c.name for c in self._registry))

    @property
    def num_classes(self) -> int:
        """Classes of the belief over this scene: background and every object class."""
        return 1 + len(self._registry)

    def object_class(self, name: str) -> ObjectClass:
        """A class of this scene (built-in or declared) by name."""
        for c in self._registry:
            if c.name == name:
                return c
        raise UserError(f"unknown object class {name!r}; known: {', '.join(c.name for c in self._registry)}")

    def to_json(self, path: str | Path) -> None:
        Path(path).write_text(self.model_dump_json(indent=2))

    @classmethod
    def from_json(cls, path: str | Path, offered: Mapping[str, ClassSpec] | None = None) -> SceneSpec:
        """Load a scene file; failures raise a ``UserError`` naming the file and the field. ``offered``:
        classes plugins declare (``MsmemPluginManager.object_classes``), used when an object names one."""
        p = Path(path)
        try:
            data = load_json(p.read_text())
        except OSError as e:
            raise UserError(f"cannot read scene file {p}: {e.strerror or e}") from e
        except json.JSONDecodeError as e:
            raise UserError(f"scene file {p} is not valid JSON: {e.msg} at line {e.lineno}") from e
        except ValueError as e:  # a duplicate key
            raise UserError(f"scene file {p} is not valid JSON: {e}") from e
        if isinstance(data, dict):
            relative_mesh_files(data.get("classes"), p.parent)
        try:
            return cls.model_validate(data, context={"offered_classes": dict(offered or {})})
        except ValidationError as e:
            raise UserError(f"invalid scene file {p}: {error_lines(e, most=3)}") from e
