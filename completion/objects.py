"""The object library: procedural families, pybullet_data meshes and user folders.

Every object has a stable string id and a split, and :func:`load_object` turns an id into a
``trimesh.Trimesh`` in metres, centred on its bounding-box centre:

- ``proc/<family>/<k>``: procedural, ``k`` ≥ 0; parameters are a function of (family, k) alone.
  Split by ``k % 10``: 0–7 train, 8 val, 9 test. Largest extent 4–25 cm.
- ``urdf/<nnn>``: ``pybullet_data/random_urdfs/nnn``, split by id: 000–799 train, 800–899 val,
  900–999 test. Rescaled to a largest extent of 4–25 cm drawn from the id.
- ``named/<name>``: the named pybullet_data meshes (mug, duck, teddy, bunny, lego, soccer ball,
  torus, toys); test only, rescaled to 8–20 cm.
- ``file:<path>``: any OBJ/STL/PLY mesh (``objects_in_folder``), used as given if its largest
  extent is 2–50 cm, otherwise rescaled to 15 cm. Test only.

Splits are by object, so no test object is ever seen in training.
"""

from __future__ import annotations

import functools
import zlib
from pathlib import Path
from typing import Literal

import numpy as np
import trimesh

Split = Literal["train", "val", "test"]
SPLITS: tuple[str, ...] = ("train", "val", "test")
SIZE_RANGE_M = (0.04, 0.25)
FAMILIES: tuple[str, ...] = (
    "box",
    "cylinder",
    "ellipsoid",
    "capsule",
    "cone",
    "torus",
    "superquadric",
    "mug",
    "bottle",
    "hammer",
    "l_shape",
    "t_shape",
)
#: Procedural ids per family (k = 0 … N-1); the split takes k % 10.
PROCEDURAL_PER_FAMILY = 1000
NAMED_OBJECTS: dict[str, str] = {
    "mug": "objects/mug.obj",
    "duck": "duck.obj",
    "teddy": "teddy2_VHACD_CHs.obj",
    "bunny": "bunny.obj",
    "lego": "lego/lego.obj",
    "soccerball": "soccerball.obj",
    "torus": "torus/torus_textured.obj",
    "toy_cylinder": "toys/cylinder.obj",
    "toy_prism": "toys/prism.obj",
    "toy_concave_box": "toys/concave_box.obj",
}
MESH_SUFFIXES = (".obj", ".stl", ".ply")
#: Library objects whose mesh cannot be used (urdf/168's OBJ has no vertices). They stay in
#: the id lists so that every seeded draw keeps its meaning; :func:`completion.scenes.make_sequence`
#: warns and redraws when it meets one. A test loads every object to keep this list true.
UNREADABLE: frozenset[str] = frozenset({"urdf/168"})


def _pybullet_data() -> Path:
    import pybullet_data

    return Path(pybullet_data.getDataPath())


def _rng_for(object_id: str) -> np.random.Generator:
    """A generator that depends only on the object id (stable across runs and machines)."""
    return np.random.default_rng(zlib.crc32(object_id.encode()))


def split_of(object_id: str) -> str:
    """The split an object id belongs to."""
    kind, _, rest = object_id.partition("/")
    if object_id.startswith("file:") or kind == "named":
        return "test"
    if kind == "proc":
        k = int(rest.rsplit("/", 1)[1])
        return "train" if k % 10 < 8 else ("val" if k % 10 == 8 else "test")
    if kind == "urdf":
        n = int(rest)
        return "train" if n < 800 else ("val" if n < 900 else "test")
    raise ValueError(f"unknown object id {object_id!r}: expected proc/…, urdf/…, named/… or file:…")


def object_ids(split: str, *, sources: tuple[str, ...] = ("proc", "urdf")) -> list[str]:
    """Every object id of ``split`` from the given sources ("proc", "urdf", "named")."""
    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    ids: list[str] = []
    if "proc" in sources:
        ids += [f"proc/{f}/{k}" for f in FAMILIES for k in range(PROCEDURAL_PER_FAMILY)]
    if "urdf" in sources:
        ids += [f"urdf/{n:03d}" for n in range(1000)]
    if "named" in sources:
        ids += [f"named/{name}" for name in NAMED_OBJECTS]
    return [i for i in ids if split_of(i) == split]


def objects_in_folder(folder: str | Path) -> list[str]:
    """Ids (``file:<path>``) of every OBJ/STL/PLY mesh in a folder, sorted."""
    root = Path(folder)
    if not root.is_dir():
        raise ValueError(
            f"--objects must be a folder of OBJ/STL/PLY meshes; {root} is not a folder"
        )
    ids = [
        f"file:{p.resolve()}" for p in sorted(root.iterdir()) if p.suffix.lower() in MESH_SUFFIXES
    ]
    if not ids:
        raise ValueError(f"no OBJ/STL/PLY meshes found in {root}")
    return ids


def load_object(object_id: str) -> trimesh.Trimesh:
    """The mesh of an object id: metres, centred on its bounding-box centre (a fresh copy)."""
    return _load_cached(object_id).copy()


@functools.lru_cache(maxsize=256)
def _load_cached(object_id: str) -> trimesh.Trimesh:
    rng = _rng_for(object_id)
    if object_id.startswith("file:"):
        mesh = read_mesh(Path(object_id[5:]))
        size = float(mesh.extents.max())
        target = size if 0.02 <= size <= 0.5 else 0.15
    else:
        kind, _, rest = object_id.partition("/")
        if kind == "proc":
            family, _, _k = rest.partition("/")
            if family not in FAMILIES:
                raise ValueError(f"unknown family {family!r}; expected one of {FAMILIES}")
            mesh = _PROCEDURAL[family](rng)
            target = rng.uniform(*SIZE_RANGE_M)
        elif kind == "urdf":
            mesh = read_mesh(_pybullet_data() / "random_urdfs" / rest / f"{rest}.obj")
            target = rng.uniform(*SIZE_RANGE_M)
        elif kind == "named":
            if rest not in NAMED_OBJECTS:
                raise ValueError(
                    f"unknown named object {rest!r}; expected one of {list(NAMED_OBJECTS)}"
                )
            mesh = read_mesh(_pybullet_data() / NAMED_OBJECTS[rest])
            target = rng.uniform(0.08, 0.20)
        else:
            split_of(object_id)  # raises the explanatory error
            raise AssertionError
    mesh.apply_translation(-mesh.bounds.mean(axis=0))
    mesh.apply_scale(target / float(mesh.extents.max()))
    return mesh


def mesh_from_spec(spec: str) -> trimesh.Trimesh:
    """What a command line's MESH argument names: a mesh file (any format trimesh reads, metres,
    as is) or an object id of the library (``named/mug``, ``proc/box/3``, ``urdf/012``)."""
    path = Path(spec)
    if path.is_file():
        return read_mesh(path)
    if spec.startswith(("proc/", "urdf/", "named/", "file:")):
        return load_object(spec)
    raise ValueError(
        f"MESH must be a mesh file or an object id (named/mug, proc/box/3, urdf/012); got {spec!r}"
    )


def read_mesh(path: Path) -> trimesh.Trimesh:
    """The triangles of a mesh file; ValueError naming the file when it holds none."""
    if not path.is_file():
        raise ValueError(f"mesh file not found: {path}")
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise ValueError(f"could not read a triangle mesh from {path}: {exc}") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise ValueError(f"{path} holds no triangles")
    if not np.isfinite(mesh.vertices).all() or mesh.extents.max() <= 0:
        raise ValueError(f"{path} has non-finite or degenerate vertices")
    return trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)


# ---------------------------------------------------------------------------------------------
# Procedural families. Each takes a generator and returns a mesh of any scale (rescaled later).


def _box(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.box(extents=rng.uniform(0.3, 1.0, 3))


def _cylinder(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=rng.uniform(0.15, 0.5), height=1.0, sections=40)


def _ellipsoid(rng: np.random.Generator) -> trimesh.Trimesh:
    mesh = trimesh.creation.icosphere(subdivisions=3)
    mesh.apply_scale(rng.uniform(0.5, 1.0, 3))
    return mesh


def _capsule(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.capsule(height=rng.uniform(0.3, 1.0), radius=rng.uniform(0.15, 0.35))


def _cone(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.cone(radius=rng.uniform(0.25, 0.6), height=1.0, sections=40)


def _torus(rng: np.random.Generator) -> trimesh.Trimesh:
    return trimesh.creation.torus(major_radius=1.0, minor_radius=rng.uniform(0.2, 0.5))


def _superquadric(rng: np.random.Generator) -> trimesh.Trimesh:
    """Star-shaped superquadric: each unit direction v is scaled to the surface F(s·v) = 1."""
    e1, e2 = rng.uniform(0.3, 1.6, 2)
    a, b, c = rng.uniform(0.5, 1.0, 3)
    mesh = trimesh.creation.icosphere(subdivisions=4)
    x, y, z = np.abs(mesh.vertices.T) / np.array([[a], [b], [c]]) + 1e-12
    f = (x ** (2 / e2) + y ** (2 / e2)) ** (e2 / e1) + z ** (2 / e1)
    mesh.vertices = mesh.vertices * (f ** (-e1 / 2))[:, None]
    return mesh


def _mug(rng: np.random.Generator) -> trimesh.Trimesh:
    r = rng.uniform(0.3, 0.45)
    h = rng.uniform(0.7, 1.1)
    wall = rng.uniform(0.06, 0.1)
    cup = trimesh.creation.annulus(r_min=r - wall, r_max=r, height=h, sections=40)
    bottom = trimesh.creation.cylinder(radius=r, height=wall, sections=40)
    bottom.apply_translation([0, 0, -h / 2 + wall / 2])
    handle = trimesh.creation.torus(
        major_radius=h * 0.28, minor_radius=wall * 0.6, major_sections=24, minor_sections=10
    )
    handle.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    handle.apply_translation([r + h * 0.12, 0, 0])
    return trimesh.util.concatenate([cup, bottom, handle])


def _bottle(rng: np.random.Generator) -> trimesh.Trimesh:
    r = rng.uniform(0.15, 0.3)
    body_h = rng.uniform(0.5, 0.7)
    neck_r = r * rng.uniform(0.3, 0.5)
    body = trimesh.creation.cylinder(radius=r, height=body_h, sections=32)
    shoulder = trimesh.creation.cone(radius=r, height=r * 0.8, sections=32)
    shoulder.apply_translation([0, 0, body_h / 2])
    neck = trimesh.creation.cylinder(radius=neck_r, height=1.0 - body_h, sections=24)
    neck.apply_translation([0, 0, body_h / 2 + (1.0 - body_h) / 2])
    return trimesh.util.concatenate([body, shoulder, neck])


def _hammer(rng: np.random.Generator) -> trimesh.Trimesh:
    t = rng.uniform(0.06, 0.1)
    handle = trimesh.creation.box(extents=[t, t, 1.0])
    head = trimesh.creation.box(extents=[rng.uniform(0.3, 0.5), t * 1.8, t * 2.2])
    head.apply_translation([0, 0, 0.5])
    return trimesh.util.concatenate([handle, head])


def _l_shape(rng: np.random.Generator) -> trimesh.Trimesh:
    t = rng.uniform(0.15, 0.3)
    d = rng.uniform(0.2, 0.6)
    a = trimesh.creation.box(extents=[1.0, t, d])
    b = trimesh.creation.box(extents=[t, rng.uniform(0.5, 1.0), d])
    b.apply_translation([-0.5 + t / 2, b.extents[1] / 2 - t / 2, 0])
    return trimesh.util.concatenate([a, b])


def _t_shape(rng: np.random.Generator) -> trimesh.Trimesh:
    t = rng.uniform(0.15, 0.3)
    d = rng.uniform(0.2, 0.6)
    top = trimesh.creation.box(extents=[1.0, t, d])
    stem_len = rng.uniform(0.5, 1.0)
    stem = trimesh.creation.box(extents=[t, stem_len, d])
    stem.apply_translation([0, -stem_len / 2 - t / 2 + 1e-3, 0])
    return trimesh.util.concatenate([top, stem])


_PROCEDURAL = {
    "box": _box,
    "cylinder": _cylinder,
    "ellipsoid": _ellipsoid,
    "capsule": _capsule,
    "cone": _cone,
    "torus": _torus,
    "superquadric": _superquadric,
    "mug": _mug,
    "bottle": _bottle,
    "hammer": _hammer,
    "l_shape": _l_shape,
    "t_shape": _t_shape,
}
assert set(_PROCEDURAL) == set(FAMILIES)
