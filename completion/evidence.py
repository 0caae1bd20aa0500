"""Registered evidence: what posed views said about a still object, fused in the world frame.

MVP fuses views without registration. When the views come with camera poses and the object
stands still (an object on a table, a robot moving its camera), each view's completion can be
carried into one world-frame grid and averaged there: view t's answer is then the mean, in log-odds,
of its own logits and every earlier view's, each moved into view t's grid with the known poses.
No training (docs/experiments.md has what else was tried).

:class:`RegisteredEvidence` is that accumulation in constant size: a :data:`SIZE`³ world grid
(placed on the first posed view's grid: its centre and axes, :data:`PITCH_SCALE` × its
pitch) holding the running mean of the views' clipped logits and how many views covered
each cell. It never grows with the views (:meth:`to_arrays`: 96 kB).

The fusion of view t (:meth:`fuse`): ``(clip(L_t) + n·m) / (1 + n)`` per voxel of view t's grid,
where m and n are the world mean and count read (trilinear) at the voxel's centre; a voxel no
earlier view covered keeps view t's logit as it is (so a first view's answer is MVP's own). Then
view t's own logits join the world mean (:meth:`add`). A still camera sending the same view again
and again therefore keeps the 1-view answer: the mean of equal logits is that logit. The mean is
kept as :func:`quantize` stores it: a restored stream continues as one that never stopped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from completion.grid import GRID_SHAPE, GRID_SIZE

#: The world grid's cells per side (constant: the evidence never grows with the views).
SIZE = 40
#: The world grid's pitch as a multiple of the first posed view's grid pitch (coarser cells frame
#: more but blur: 32 cells at 1.5 lost 0.005 J on camera pan and tabletop against 40 at 1.0).
PITCH_SCALE = 1.0
#: Logits are clipped to ±this before they are averaged (a saturated view cannot outvote the
#: others by its magnitude alone).
CLIP = 6.0
#: A cell counts at most this many views (4 bits stored); past it the mean keeps moving as a
#: running average with this weight (each new view 1/15 of it).
MAX_COUNT = 15
#: Every voxel index of a view's grid (n, 3), read by :meth:`RegisteredEvidence.seen`.
_VOXELS = np.indices(GRID_SHAPE).reshape(3, -1).T
#: Stored logits (the evidence's mean, a registered completion) are int8 in steps of CLIP / 127:
#: a decision at any threshold between 0.003 and 0.997 moves by at most half a step (0.024).
STEP = CLIP / 127.0


@dataclass
class RegisteredEvidence:
    """A world-frame running mean of posed views' logits (:data:`SIZE`³ cells)."""

    grid_to_world: np.ndarray  # (4, 4): cell index -> world point at the cell centre
    mean: np.ndarray  # (SIZE,)*3 float32, clipped logits averaged over the views covering a cell
    count: np.ndarray  # (SIZE,)*3 uint8, views that covered the cell (at most MAX_COUNT)
    surface: np.ndarray | None = None  # (SIZE,)*3 bool, cells where a view saw object surface

    def __post_init__(self) -> None:
        if self.surface is None:
            self.surface = np.zeros((SIZE,) * 3, dtype=bool)

    @classmethod
    def around(cls, grid_to_camera: np.ndarray, camera_to_world: np.ndarray) -> RegisteredEvidence:
        """Empty evidence placed on a view's grid: its centre and axes, its pitch scaled (with
        :data:`PITCH_SCALE` 1 and :data:`SIZE` 40, that grid itself: a camera that stays where it
        was reads the evidence back without interpolating)."""
        view = camera_to_world @ grid_to_camera
        centre = view[:3, :3] @ np.full(3, (GRID_SIZE - 1) / 2.0) + view[:3, 3]
        grid_to_world = np.eye(4)
        grid_to_world[:3, :3] = view[:3, :3] * PITCH_SCALE
        grid_to_world[:3, 3] = centre - grid_to_world[:3, :3] @ np.full(3, (SIZE - 1) / 2.0)
        shape = (SIZE,) * 3
        return cls(grid_to_world, np.zeros(shape, np.float32), np.zeros(shape, np.uint8))

    # ------------------------------------------------------------------ the two operations
    def fuse(self, logits: np.ndarray, grid_to_camera: np.ndarray,
             camera_to_world: np.ndarray, *, own: bool = True) -> np.ndarray:
        """(40, 40, 40) float32: a view's logits (in its grid) averaged with the evidence;
        ``own=False`` (a view that showed no object points): the evidence alone where it has any,
        the view's logits elsewhere."""
        view_to_cells = np.linalg.inv(self.grid_to_world) @ camera_to_world @ grid_to_camera
        # the sum and the count, each fading to 0 over the half cell past the border cells
        total = _read(self.count * self.mean, view_to_cells, GRID_SIZE)
        count = _read(self.count.astype(np.float32), view_to_cells, GRID_SIZE)
        weight = 1.0 if own else np.where(count > 0, 0.0, 1.0).astype(np.float32)
        fused = (weight * np.clip(logits, -CLIP, CLIP) + total) / (weight + count)
        return np.where(count > 0, fused, logits).astype(np.float32)

    def add(self, logits: np.ndarray, grid_to_camera: np.ndarray,
            camera_to_world: np.ndarray) -> None:
        """Let a view's logits (in its grid) join the mean of every cell its grid covers."""
        cells_to_view = np.linalg.inv(camera_to_world @ grid_to_camera) @ self.grid_to_world
        value = _read(np.clip(logits, -CLIP, CLIP), cells_to_view, SIZE)
        covered = _covered(cells_to_view, SIZE)
        n = np.minimum(self.count[covered].astype(np.float32) + 1, MAX_COUNT)
        self.mean[covered] += (value[covered] - self.mean[covered]) / n
        self.count[covered] = n.astype(np.uint8)
        self.mean = dequantize(quantize(self.mean))

    def seen(self, grid_to_camera: np.ndarray, camera_to_world: np.ndarray) -> np.ndarray:
        """(40, 40, 40) bool: the surface earlier views saw, in a view's grid (each voxel takes
        the world cell its centre falls in): the second input channel of a model with
        ``registered_input``."""
        view_to_cells = np.linalg.inv(self.grid_to_world) @ camera_to_world @ grid_to_camera
        cells, inside = _nearest_cells(_VOXELS, view_to_cells)
        out = np.zeros(GRID_SIZE**3, dtype=bool)
        out[inside] = self.surface[tuple(cells.T)]
        return out.reshape(GRID_SHAPE)

    def add_surface(self, occupancy: np.ndarray, grid_to_camera: np.ndarray,
                    camera_to_world: np.ndarray) -> None:
        """Mark the world cells a view's observed voxels (its input grid) fall in."""
        view_to_cells = np.linalg.inv(self.grid_to_world) @ camera_to_world @ grid_to_camera
        cells, _ = _nearest_cells(np.argwhere(occupancy), view_to_cells)
        self.surface[tuple(cells.T)] = True

    # ------------------------------------------------------------------ persistence
    def to_arrays(self, prefix: str) -> dict[str, np.ndarray]:
        """The evidence as named arrays: the mean as :func:`quantize` keeps it (64 kB), the count
        two cells a byte (32 kB)."""
        count = self.count.reshape(-1)
        return {f"{prefix}grid_to_world": self.grid_to_world,
                f"{prefix}mean": quantize(self.mean),
                f"{prefix}count": (count[0::2] << 4 | count[1::2]).astype(np.uint8),
                f"{prefix}surface": np.packbits(self.surface.reshape(-1))}

    @classmethod
    def from_arrays(cls, arrays, prefix: str) -> RegisteredEvidence | None:
        """The evidence stored by :meth:`to_arrays`, checked (the bytes came from storage); None
        when there is none."""
        if f"{prefix}mean" not in arrays:
            return None
        grid_to_world = np.asarray(arrays[f"{prefix}grid_to_world"], dtype=np.float64)
        mean = np.asarray(arrays[f"{prefix}mean"])
        shape = (SIZE,) * 3
        packed = np.asarray(arrays[f"{prefix}count"])
        if (grid_to_world.shape != (4, 4) or not np.isfinite(grid_to_world).all()
                or mean.shape != shape or mean.dtype != np.int8
                or packed.shape != (SIZE**3 // 2,) or packed.dtype != np.uint8):
            raise ValueError("stored registered evidence is malformed")
        count = np.stack([packed >> 4, packed & 15], axis=1).reshape(shape)
        surface = None  # states stored before the surface was kept: none seen
        if f"{prefix}surface" in arrays:
            bits = np.asarray(arrays[f"{prefix}surface"])
            if bits.shape != (SIZE**3 // 8,) or bits.dtype != np.uint8:
                raise ValueError("stored registered evidence is malformed")
            surface = np.unpackbits(bits).astype(bool).reshape(shape)
        return cls(grid_to_world, dequantize(mean), count.astype(np.uint8), surface)


def registered_surfaces(inputs: np.ndarray, grid_to_camera: np.ndarray,
                        camera_to_world: np.ndarray) -> np.ndarray:
    """(L, 40, 40, 40) bool: for each view of a posed sequence of a still object (a shard's
    ``inputs``, ``grid_to_camera``, ``camera_to_world``), the surface the views before it saw,
    in its grid, as :class:`completion.stream.CompletionStream` gives a ``registered_input``
    model: the evidence is placed on the first view with object points; a view without points
    adds nothing."""
    out = np.zeros(np.shape(inputs), dtype=bool)
    evidence = None
    for t, occupancy in enumerate(inputs):
        if evidence is None:
            if not occupancy.any():
                continue
            evidence = RegisteredEvidence.around(grid_to_camera[t], camera_to_world[t])
        out[t] = evidence.seen(grid_to_camera[t], camera_to_world[t])
        evidence.add_surface(occupancy, grid_to_camera[t], camera_to_world[t])
    return out


def quantize(logits: np.ndarray) -> np.ndarray:
    """Logits clipped to ±:data:`CLIP` as int8 steps of :data:`STEP`."""
    return np.round(np.clip(logits, -CLIP, CLIP) / STEP).astype(np.int8)


def dequantize(steps: np.ndarray) -> np.ndarray:
    return steps.astype(np.float32) * np.float32(STEP)


def _read(volume: np.ndarray, out_to_in: np.ndarray, size: int) -> np.ndarray:
    """``volume`` read (trilinear) at the cell centres of a ``size``³ grid whose index maps into
    the volume's by the affine ``out_to_in`` (4×4): its border cells reach half a cell further
    (so a grid's own centres read back exactly), then the value fades to 0 over one cell."""
    padded = np.pad(np.pad(volume.astype(np.float32), 1, mode="edge"), 1)
    return ndimage.affine_transform(padded, out_to_in[:3, :3], out_to_in[:3, 3] + 2.0,
                                    output_shape=(size,) * 3, output=np.float32, order=1,
                                    mode="constant", prefilter=False)


def _nearest_cells(index: np.ndarray, view_to_cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The world cells (m, 3) that voxel indices (n, 3) of a view's grid fall in, and which of
    the n fall inside the world grid (n,) bool."""
    # elementwise, not ``index @ A.T``: a BLAS call here leaves OpenBLAS's threads spinning while
    # the model steps next (measured: the posed model's step 10 ms alone, 25-100 ms after it)
    a, shift = view_to_cells[:3, :3], view_to_cells[:3, 3]
    cells = index[:, :1] * a[:, 0] + index[:, 1:2] * a[:, 1] + index[:, 2:3] * a[:, 2] + shift
    cells = np.rint(cells).astype(np.int64)
    inside = np.all((cells >= 0) & (cells < SIZE), axis=1)
    return cells[inside], inside


def _covered(out_to_in: np.ndarray, size: int) -> np.ndarray:
    """(size,)*3 bool: which cell centres of that grid fall in the 40³ grid's cells."""
    index = np.indices((size,) * 3, dtype=np.float32).reshape(3, -1)
    inner = out_to_in[:3, :3].astype(np.float32) @ index + out_to_in[:3, 3:].astype(np.float32)
    return np.all((inner >= -0.5) & (inner < GRID_SIZE - 0.5), axis=0).reshape((size,) * 3)
