"""Cleaning a depth camera's input before it becomes a grid: the one place of its parameters.

A real depth camera does not only add noise: where a foreground surface meets a far background,
the returns of both mix and a pixel lands somewhere between them (a *flying pixel*, or veil
point), floating behind the object's silhouette (:class:`completion.depth_camera.SensorModel` draws
them; a real D415 or Kinect shows the same). Left in, they stretch the grid fitted to the points
and are completed as object. Two rules remove them, the same for the training data, the
evaluation and the service (every depth image becomes points through
:func:`completion.grid.depth_to_points`, which applies :meth:`DepthFilter.supported`; every grid
of observed points is fitted through :func:`completion.grid.fit_seen`, which applies
:meth:`DepthFilter.inliers`):

1. **In the image, a pixel needs support.** Pixel p at depth z and a neighbour n at lateral
   distance l = z·√((Δu/fx)² + (Δv/fy)²) are *continuous* when the segment between their points
   makes at least ``min_angle_deg`` with p's viewing ray: |z_n − z| ≤ l / tan(``min_angle_deg``),
   the veil test of ROS's laser ``ScanShadowsFilter`` and PCL's shadow-point filter (10° is
   ROS's default ``min_angle``). A pixel is kept when at least ``min_support`` of its 8
   neighbours are continuous with it: a surface pixel has several (up to 80° of slant), a thin
   handle one or two pixels wide has its neighbours along the handle, a flying pixel hanging
   behind the rim has none once it is more than l / tan 10° (about 1 cm at 0.6 m) from it.
   Only pixels of the object's mask count as neighbours, where there is a mask: a flying pixel
   that fell almost onto the table behind the rim is not held up by the table.
2. **The grid's box ignores sparse points.** The Varley fit frames the bounding box of the
   observed points; a point counts toward it only when the 3 × 3 × 3 cube of ``outlier_cell_m``
   (1 cm) cells around it holds at least ``outlier_neighbours`` (4) other points and at least
   ``outlier_share`` (3 %) of what the cloud's median point has around it: a density rule, as
   PCL's radius and statistical outlier removals are, relative so that a thin sheet of strays
   (1 % of a view's points 5 cm behind the surface) is as sparse as a lone one. A rendered
   surface at 0.3–2 m, a face seen edge-on or a handle included, is far denser, so on a clean
   view the box is the plain one (on the noiseless test views checked: the same on most, the
   side 0.3 % smaller on average where a far sparse part is left out). A cloud too sparse for
   the rule (fewer than half its points pass, e.g. a handful of points a client sent) is
   framed whole, as before.

Points a client sends as points are taken as given by rule 1 (there is no image); rule 2 frames
them like any other. Only numpy and scipy live here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_CUBE = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)])
_NEIGHBOURS = tuple((dv, du) for dv in (-1, 0, 1) for du in (-1, 0, 1) if (dv, du) != (0, 0))


@dataclass(frozen=True)
class DepthFilter:
    """The input cleaning's parameters (metres, pixels, degrees); see the module's docstring."""

    #: Smallest angle (degrees) between a pixel's viewing ray and the segment to a neighbour that
    #: still counts as one surface (ROS ScanShadowsFilter's default ``min_angle``).
    min_angle_deg: float = 10.0
    #: Continuous 8-neighbours a pixel needs to be kept.
    min_support: int = 2
    #: A point frames the grid when the cube of 3 × 3 × 3 cells of ``outlier_cell_m`` around it
    #: holds at least ``outlier_neighbours`` other points and at least ``outlier_share`` of the
    #: cloud's median such count.
    outlier_cell_m: float = 0.01
    outlier_neighbours: int = 4
    outlier_share: float = 0.03

    def __post_init__(self) -> None:
        if not 0.0 < self.min_angle_deg < 90.0:
            raise ValueError(f"min_angle_deg must be in (0, 90), got {self.min_angle_deg}")
        if not 0 <= self.min_support <= 8:
            raise ValueError(f"min_support must be 0-8 neighbours, got {self.min_support}")
        if self.outlier_cell_m <= 0 or self.outlier_neighbours < 0:
            raise ValueError("outlier_cell_m must be > 0 and outlier_neighbours ≥ 0")
        if not 0 <= self.outlier_share < 1:
            raise ValueError(f"outlier_share must be in [0, 1), got {self.outlier_share}")

    def supported(
        self, depth: np.ndarray, fx: float, fy: float, mask: np.ndarray | None = None
    ) -> np.ndarray:
        """(H, W) bool: pixels with a return (finite, > 0) and at least ``min_support``
        continuous neighbours; ``fx``, ``fy`` the focal lengths in pixels. With a ``mask`` (H, W)
        bool, only pixels inside it support (the table behind an object's rim does not hold a
        flying pixel up) and only they are kept."""
        z = np.asarray(depth, dtype=np.float64)
        hit = np.isfinite(z) & (z > 0)
        if mask is not None:
            hit &= np.asarray(mask, dtype=bool)
        z = np.where(hit, z, 0.0)
        if self.min_support == 0:
            return hit
        padded = np.pad(z, 1)
        h, w = z.shape
        slope = 1.0 / math.tan(math.radians(self.min_angle_deg))
        count = np.zeros(z.shape, dtype=np.int8)
        gap, tolerance = np.empty_like(z), np.empty_like(z)  # reused: a large image stays cheap
        for dv, du in _NEIGHBOURS:
            nb = padded[1 + dv : 1 + dv + h, 1 + du : 1 + du + w]
            np.abs(np.subtract(nb, z, out=gap), out=gap)
            np.multiply(z, math.hypot(du / fx, dv / fy) * slope, out=tolerance)
            count += (nb > 0) & (gap <= tolerance)
        return hit & (count >= self.min_support)

    def inliers(self, points: np.ndarray) -> np.ndarray:
        """(n,) bool: the points that frame the grid (rule 2); all of them for a sparse cloud."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        keep = np.ones(len(pts), dtype=bool)
        if len(pts) <= self.outlier_neighbours:
            return keep
        cell = np.floor(pts / self.outlier_cell_m).astype(np.int64)
        cell -= cell.min(axis=0) - 1  # ≥ 1, so that every neighbouring cell has an index ≥ 0
        dims = tuple(int(d) for d in cell.max(axis=0) + 2)
        keys, inverse, counts = np.unique(np.ravel_multi_index(cell.T, dims), return_inverse=True,
                                          return_counts=True)
        del cell
        occupied = np.stack(np.unravel_index(keys, dims), axis=1)  # per occupied cell, not point
        per_cell = np.zeros(len(keys), dtype=np.int64)
        for offset in _CUBE:
            key = np.ravel_multi_index((occupied + offset).T, dims)
            at = np.minimum(np.searchsorted(keys, key), len(keys) - 1)
            per_cell += np.where(keys[at] == key, counts[at], 0)
        around = per_cell[inverse.reshape(-1)] - 1  # not counting the point itself
        dense = (around >= self.outlier_neighbours) & (
            around >= self.outlier_share * float(np.median(around)))
        return dense if dense.sum() * 2 >= len(pts) else keep


#: The filter every depth image and every observed point cloud goes through.
DEPTH_FILTER = DepthFilter()
