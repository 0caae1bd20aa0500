"""The object's rigid body for a lift test: convex pieces (V-HACD, cached), mass and inertia."""

from __future__ import annotations

import hashlib
import logging
import os
import tempfile
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import ConvexHull, HalfspaceIntersection, QhullError

from completion.bullet import direct_client, quiet_fds
from grasp.hand.collision import check_mesh
from grasp.physics.settings import DENSITY_KG_M3, VHACD_OPTIONS

log = logging.getLogger(__name__)
_CACHE_VERSION = "1"
#: Most meshes the convex-decomposition cache keeps (about 23 KB each: some 23 MB) unless
#: ``GRASP_CONVEX_CACHE_ENTRIES`` says otherwise; past it the least recently used go first (a hit
#: renews an entry's time), so a long-running service that sees a new completion at every view does
#: not fill the disk.
CACHE_ENTRIES = 1000
#: The environment's settings of the cache, read at each use (the service's planner processes
#: inherit them): its folder and its bound.
CACHE_DIR_ENV, CACHE_ENTRIES_ENV = "GRASP_CONVEX_CACHE_DIR", "GRASP_CONVEX_CACHE_ENTRIES"


def _cache_root(cache_dir: str | Path | None) -> Path:
    if cache_dir is not None:
        return Path(cache_dir)
    if os.environ.get(CACHE_DIR_ENV):
        return Path(os.environ[CACHE_DIR_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mvp-grasp" / "convex"


def cache_entries() -> int:
    """The cache's bound: ``GRASP_CONVEX_CACHE_ENTRIES``, else :data:`CACHE_ENTRIES`."""
    given = os.environ.get(CACHE_ENTRIES_ENV)
    if not given:
        return CACHE_ENTRIES
    if not given.isdigit() or int(given) < 1:
        raise ValueError(f"{CACHE_ENTRIES_ENV} must be a whole number of meshes, at least 1; "
                         f"got {given!r}")
    return int(given)


def _mesh_key(mesh: trimesh.Trimesh) -> str:
    digest = hashlib.sha256()
    digest.update(_CACHE_VERSION.encode())
    digest.update(repr(sorted(VHACD_OPTIONS.items())).encode())
    digest.update(np.ascontiguousarray(mesh.vertices, dtype="<f8").tobytes())
    digest.update(np.ascontiguousarray(mesh.faces, dtype="<i8").tobytes())
    return digest.hexdigest()[:32]


def write_pieces(path: Path, pieces: Sequence[np.ndarray]) -> None:
    """Write the convex hulls of pieces ((k, 3) vertex arrays) as one OBJ, an ``o`` group each
    (pybullet makes one convex collision shape per group)."""
    scene = trimesh.Scene()
    for index, vertices in enumerate(pieces):
        name = f"convex_{index}"
        scene.add_geometry(trimesh.convex.convex_hull(vertices), geom_name=name, node_name=name)
    text = trimesh.exchange.obj.export_obj(
        scene, include_normals=False, include_texture=False, header=None
    )
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)  # atomic: a concurrent reader sees the old file or the new one


def read_pieces(path: str | Path) -> list[np.ndarray]:
    """The vertex arrays ((k, 3) float each) of the convex pieces in an OBJ: its connected
    components (V-HACD and :func:`write_pieces` write each hull with its own vertices)."""
    mesh = trimesh.load(Path(path), file_type="obj", force="mesh", process=False)
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        return []
    parts = mesh.split(only_watertight=False)
    return [np.asarray(p.vertices, dtype=np.float64) for p in parts if len(p.vertices) >= 4]


def convex_decomposition(
    mesh: trimesh.Trimesh, *, cache_dir: str | Path | None = None
) -> tuple[Path, list[np.ndarray]]:
    """Convex pieces of ``mesh`` as an OBJ file (one ``o`` group per hull) and their vertices.

    A convex mesh is its own hull; anything else goes through pybullet's V-HACD
    (:data:`VHACD_OPTIONS`). The OBJ is cached under ``cache_dir`` (default
    ``$GRASP_CONVEX_CACHE_DIR``, else ``$XDG_CACHE_HOME/mvp-grasp/convex`` or ``~/.cache/…``,
    falling back to the temp folder when that is not writable) by a hash of the vertices, faces
    and options, so the same mesh in the same pose is decomposed once; the cache keeps the
    :func:`cache_entries` most recently used.

    Returns
    -------
    (path, pieces): the OBJ path and a list of (k, 3) float vertex arrays, mesh coordinates.
    """
    check_mesh(mesh)
    root = _cache_root(cache_dir)
    try:
        root.mkdir(parents=True, exist_ok=True)
    except OSError:
        if cache_dir is not None or os.environ.get(CACHE_DIR_ENV):
            raise
        root = Path(tempfile.gettempdir()) / "mvp-grasp-convex"
        root.mkdir(parents=True, exist_ok=True)
    path = root / f"{_mesh_key(mesh)}.obj"
    if not _renewed(path):  # not cached (or evicted by another process just now)
        if mesh.is_convex:
            write_pieces(path, [np.asarray(mesh.vertices)])
        else:
            log.info("V-HACD decomposition of a %d-face mesh into %s", len(mesh.faces), path)
            with tempfile.TemporaryDirectory() as tmp:
                source, result = Path(tmp) / "in.obj", Path(tmp) / "out.obj"
                source.write_text(trimesh.exchange.obj.export_obj(mesh, include_normals=False))
                client = direct_client()
                try:
                    with quiet_fds(1):  # V-HACD prints its progress on stdout
                        client.vhacd(
                            str(source), str(result), str(Path(tmp) / "log.txt"), **VHACD_OPTIONS
                        )
                finally:
                    client.disconnect()
                pieces = read_pieces(result) if result.is_file() else []
            if not pieces:  # V-HACD gave nothing usable: fall back to the hull
                log.warning("V-HACD returned no pieces; using the convex hull")
                pieces = [np.asarray(mesh.vertices)]
            write_pieces(path, pieces)
        _evict(root, cache_entries())
    return path, read_pieces(path)


def _renewed(path: Path) -> bool:
    """Mark a cached entry used now (the last to be evicted); False when there is none."""
    try:
        os.utime(path)
    except FileNotFoundError:
        return False
    except OSError:  # a cache this process may read but not write: used as it is
        pass
    return True


def _evict(root: Path, keep: int) -> None:
    """Delete all but the ``keep`` most recently used OBJ files of the cache folder."""
    entries = []
    for path in root.glob("*.obj"):
        try:
            entries.append((path.stat().st_mtime, path))
        except OSError:  # deleted by another process since the listing
            continue
    entries.sort()
    for _, path in entries[: max(len(entries) - keep, 0)]:
        path.unlink(missing_ok=True)


def shrink(vertices: np.ndarray, margin: float) -> np.ndarray:
    """Vertices (k, 3) of the convex hull of ``vertices`` with every face moved ``margin`` inward.

    A piece too thin to shrink (its centroid closer than ``margin`` to a face) is returned as is.
    """
    try:
        hull = ConvexHull(vertices)
    except QhullError:
        return vertices
    centre = vertices[hull.vertices].mean(axis=0)
    equations = hull.equations.copy()  # (f, 4): n·x + d <= 0 inside, |n| = 1
    if not np.all(equations[:, :3] @ centre + equations[:, 3] < -2.0 * margin):
        return vertices
    equations[:, 3] += margin
    try:
        return HalfspaceIntersection(equations, centre).intersections
    except QhullError:
        return vertices


def mass_properties(
    mesh: trimesh.Trimesh, pieces: Sequence[np.ndarray], density: float = DENSITY_KG_M3
) -> tuple[float, np.ndarray, np.ndarray]:
    """Mass (kg), centre of mass (3,) and inertia tensor about it (3, 3), at ``density``.

    From the mesh when it is a closed, consistently wound volume; otherwise the sum over the convex
    ``pieces`` (overlaps counted twice, which V-HACD keeps small).
    """
    if not density > 0.0:
        raise ValueError(f"density must be positive (kg/m³), got {density}")
    parts = [mesh] if mesh.is_volume else [trimesh.convex.convex_hull(p) for p in pieces]
    props = [trimesh.triangles.mass_properties(p.triangles, density=density) for p in parts]
    masses = np.array([p.mass for p in props])
    if not masses.sum() > 0.0:
        raise ValueError("the object has no volume; cannot give it a mass")
    centres = np.array([p.center_mass for p in props])
    com = masses @ centres / masses.sum()
    inertia = np.zeros((3, 3))
    for p, m, c in zip(props, masses, centres, strict=True):
        d = c - com
        inertia += np.asarray(p.inertia) + m * (d @ d * np.eye(3) - np.outer(d, d))
    return float(masses.sum()), com, inertia
