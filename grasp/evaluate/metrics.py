"""Completion and grasp metrics of the paper's Tables I–III (docs/design.md §6–§7).

- :func:`jaccard`: intersection over union of two thresholded 40³ grids.
- :func:`fscore` / :func:`fscore_grids`: F-score@d after Tatarchenko et al. 2019
  (lmb-freiburg/what3d): the prediction is meshed (:func:`completion.mesh.grid_to_mesh`) and
  compared with the true objects' surfaces inside the grid (:func:`truth_surface_sample`); each
  side is sampled independently (its own seed) and densely, :data:`SAMPLES_PER_VOXEL_AREA` points
  per voxel face of area (at least 8,192), so that two samples of one surface score F@1% ≥ 0.98
  (d is only 0.4 voxel) and the score measures the surfaces, not the sampling. Precision is the
  share of predicted points with a true point closer than d (strict ``<``), recall the converse,
  and F = 2PR / (P + R). d is a fraction of the grid side (40 × pitch): 1% and 2% by default.
  A perfect completion (the 40³ target itself) scores the protocol's ceiling, below 1 because
  the grid is coarser than the object.
- :func:`grasp_joint_error`: plan on the predicted mesh, re-grasp the ground truth from the same
  pre-grasp pose, mean |Δθ| over the 8 BarrettHand joints in degrees (and per joint, and over the
  6 that move: the re-grasp keeps the planned spread, so the two spread joints never differ and
  the 8-joint mean is 0.75 × the 6-joint one).

Conventions for degenerate cases (stated once, used by the evaluation):

- Jaccard of two empty grids is 1 (they agree); of one empty and one non-empty grid, 0.
- F-score: an empty prediction (nothing at the threshold, so no surface) scores 0; an empty
  prediction against an empty ground truth scores 1. Precision, recall and F are 0 when either
  side has no points.
- Joint error: when the prediction has no surface or the planner finds no grasp on it, there is
  no grasp to compare; :class:`JointError` says so (``error_deg`` is None with the reason) and the
  evaluation counts these cases separately instead of averaging them in.

Only numpy, scipy and trimesh here (the grasp modules are imported where used): no torch.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from completion.grid import GRID_SHAPE, GRID_SIZE, pitch_of, transform_points
from completion.grid import jaccard as grid_jaccard
from completion.mesh import EmptyMeshError, grid_to_mesh
from hands.barrett import JOINT_NAMES  # the 8 joints, in the order of every joint array here

__all__ = [
    "FSCORE_FRACTIONS",
    "FSCORE_SAMPLES",
    "JOINT_NAMES",
    "FScore",
    "JointError",
    "MOVING_JOINTS",
    "SAMPLES_PER_VOXEL_AREA",
    "SurfaceSample",
    "dense_count",
    "fscore",
    "fscore_grids",
    "grasp_joint_error",
    "grid_side",
    "grid_surface_sample",
    "jaccard",
    "mesh_or_none",
    "sample_surface",
    "truth_surface_sample",
]

#: Fewest points sampled on a surface for the F-score.
FSCORE_SAMPLES = 8192
#: Points of each side whose nearest neighbour is looked up (a random subset of the sample: the
#: shares P and R are estimated to a standard error under 0.8 %).
FSCORE_QUERIES = 4096
#: F-score sampling density: points per voxel face of surface area (pitch²). A Poisson sample of
#: this density leaves a point of a second sample of the same surface without a neighbour closer
#: than 0.4 voxel with probability exp(-10·π·0.4²) ≈ 0.7 %.
SAMPLES_PER_VOXEL_AREA = 10.0
#: The joints that move in a re-grasp (the spread is kept from the planned grasp).
MOVING_JOINTS: tuple[str, ...] = tuple(j for j in JOINT_NAMES if "spread" not in j)
_MOVING = np.array([j in MOVING_JOINTS for j in JOINT_NAMES])
#: Distance thresholds as fractions of the grid side length (40 × pitch).
FSCORE_FRACTIONS: tuple[float, ...] = (0.01, 0.02)


# ------------------------------------------------------------------------------------- Jaccard


def jaccard(prediction: np.ndarray, target: np.ndarray) -> float:
    """|A ∩ B| / |A ∪ B| of two (40, 40, 40) bool grids (1 when both are empty)."""
    a, b = _as_grid(prediction, "prediction"), _as_grid(target, "target")
    return float(grid_jaccard(a, b))


def _as_grid(grid: np.ndarray, name: str) -> np.ndarray:
    g = np.asarray(grid)
    if g.shape != GRID_SHAPE:
        raise ValueError(f"{name} must be a {GRID_SHAPE} grid, got shape {g.shape}")
    if g.dtype != bool:
        raise ValueError(
            f"{name} must be a bool grid (threshold probabilities first), got {g.dtype}"
        )
    return g


# ------------------------------------------------------------------------------------- F-score


@dataclass(frozen=True)
class SurfaceSample:
    """Points sampled on a surface, with their KD-tree (built once, queried by every comparison).

    points : (n, 3) float, metres; n = 0 for an empty surface.
    """

    points: np.ndarray
    tree: cKDTree | None

    @classmethod
    def empty(cls) -> SurfaceSample:
        return cls(np.zeros((0, 3)), None)

    @property
    def is_empty(self) -> bool:
        return len(self.points) == 0


def dense_count(mesh: trimesh.Trimesh, pitch: float) -> int:
    """Points to sample on ``mesh`` for :data:`SAMPLES_PER_VOXEL_AREA` per voxel face of area."""
    return max(FSCORE_SAMPLES, int(np.ceil(SAMPLES_PER_VOXEL_AREA * mesh.area / pitch**2)))


def sample_surface(
    mesh: trimesh.Trimesh | None,
    *,
    count: int | None = FSCORE_SAMPLES,
    seed: int = 0,
    pitch: float | None = None,
) -> SurfaceSample:
    """Area-uniform points on ``mesh`` (seeded): ``count`` of them, or with ``count=None`` as
    many as :func:`dense_count` asks at voxel size ``pitch``; an empty sample for ``None``."""
    if mesh is None or len(mesh.faces) == 0 or mesh.area <= 0:
        return SurfaceSample.empty()
    if count is None:
        if pitch is None or not pitch > 0:
            raise ValueError(f"a density-based sample needs the voxel pitch, got {pitch}")
        count = dense_count(mesh, pitch)
    if count < 1:
        raise ValueError(f"count must be >= 1, got {count}")
    points, _ = trimesh.sample.sample_surface(mesh, count, seed=seed)
    points = np.asarray(points, dtype=np.float64)
    return SurfaceSample(points, _tree(points))


def _tree(points: np.ndarray) -> cKDTree:
    # unbalanced and not compacted: builds twice as fast; queries here are few and short
    return cKDTree(points, balanced_tree=False, compact_nodes=False)


@dataclass(frozen=True)
class FScore:
    """F-score, precision and recall at one distance threshold ``d`` (metres)."""

    d: float
    fscore: float
    precision: float
    recall: float


def fscore(
    prediction: SurfaceSample,
    target: SurfaceSample,
    thresholds: Sequence[float],
    *,
    queries: int = FSCORE_QUERIES,
) -> list[FScore]:
    """F-score at each distance threshold (metres), strict ``<`` as in Tatarchenko et al. 2019.

    P(d) = share of predicted points whose nearest target point is closer than d;
    R(d) = share of target points whose nearest predicted point is closer than d;
    F(d) = 2PR / (P + R), 0 when P + R = 0. Both empty: F = 1; one empty: F = 0.

    Each share is estimated on the first ``queries`` points of a side (a random subset, as the
    samples are i.i.d.; standard error under 0.8 %) while the nearest neighbours are searched
    among all the other side's points: the density that matters is the searched side's.
    """
    ds = [float(d) for d in thresholds]
    if not ds or any(not np.isfinite(d) or d <= 0 for d in ds):
        raise ValueError(f"thresholds must be positive distances in metres, got {thresholds}")
    if prediction.is_empty or target.is_empty:
        both = prediction.is_empty and target.is_empty
        return [FScore(d, float(both), float(both), float(both)) for d in ds]
    bound = max(ds)
    # Distances at or beyond the largest threshold come back as inf, which saves most of the work.
    to_target, _ = target.tree.query(
        prediction.points[:queries], k=1, distance_upper_bound=bound
    )
    to_prediction, _ = prediction.tree.query(
        target.points[:queries], k=1, distance_upper_bound=bound
    )
    out = []
    for d in ds:
        p = float(np.mean(to_target < d))
        r = float(np.mean(to_prediction < d))
        f = 2 * p * r / (p + r) if p + r > 0 else 0.0
        out.append(FScore(d, f, p, r))
    return out


def grid_side(grid_to_camera: np.ndarray) -> float:
    """Side length of the 40³ grid in metres (40 × pitch)."""
    return GRID_SIZE * pitch_of(grid_to_camera)


def mesh_or_none(
    probabilities: np.ndarray,
    grid_to_camera: np.ndarray,
    *,
    threshold: float,
    oriented: bool = True,
) -> trimesh.Trimesh | None:
    """:func:`completion.mesh.grid_to_mesh`, or None when nothing reaches the threshold."""
    try:
        return grid_to_mesh(probabilities, grid_to_camera, threshold=threshold, oriented=oriented)
    except EmptyMeshError:
        return None


def grid_surface_sample(
    probabilities: np.ndarray,
    grid_to_camera: np.ndarray,
    *,
    threshold: float,
    count: int | None = None,
    seed: int = 0,
) -> SurfaceSample:
    """Mesh a grid (marching cubes at ``threshold``) and sample its surface (densely unless a
    ``count`` is given)."""
    mesh = mesh_or_none(probabilities, grid_to_camera, threshold=threshold, oriented=False)
    return sample_surface(mesh, count=count, seed=seed, pitch=pitch_of(grid_to_camera))


def truth_surface_sample(
    meshes: Sequence[trimesh.Trimesh], grid_to_camera: np.ndarray, *, seed: int = 0
) -> SurfaceSample:
    """Dense sample of the true objects' surfaces (meshes in the grid's camera frame), keeping
    the points that lie inside the 40³ grid: what a completion in this grid can reach."""
    if not meshes:
        return SurfaceSample.empty()
    mesh = trimesh.util.concatenate(list(meshes))
    pitch = pitch_of(grid_to_camera)
    sample = sample_surface(mesh, count=None, seed=seed, pitch=pitch)
    if sample.is_empty:
        return sample
    index = transform_points(sample.points, np.linalg.inv(grid_to_camera))
    inside = np.all((index >= -0.5) & (index <= GRID_SIZE - 0.5), axis=1)
    points = sample.points[inside]
    # balanced: this tree is built once per view and searched by every row
    return SurfaceSample(points, cKDTree(points)) if len(points) else SurfaceSample.empty()


def fscore_grids(
    probabilities: np.ndarray,
    truth: SurfaceSample,
    grid_to_camera: np.ndarray,
    *,
    threshold: float,
    fractions: Sequence[float] = FSCORE_FRACTIONS,
    seed: int = 0,
) -> list[FScore]:
    """F-score of a predicted grid (one view) against a sample of the true surface.

    probabilities : (40, 40, 40) float in [0, 1] (or bool), meshed at ``threshold`` and sampled
        densely with ``seed`` (use a seed other than the truth sample's: independent samples)
    truth : :func:`truth_surface_sample` of the view (built once, shared by every row)
    fractions : distance thresholds as fractions of the grid side (40 × pitch)
    """
    side = grid_side(grid_to_camera)
    pred = grid_surface_sample(probabilities, grid_to_camera, threshold=threshold, seed=seed)
    return fscore(pred, truth, [f * side for f in fractions])


# ------------------------------------------------------------------------------------- grasp


@dataclass(frozen=True)
class JointError:
    """Grasp joint error of one prediction (docs/design.md §7).

    error_deg : mean |θ_pred − θ_gt| over the 8 joints, None when there was no grasp to compare
    per_joint_deg : (8,) |θ_pred − θ_gt| in the joint order of :data:`JOINT_NAMES`, or None
    planned : the planner's best grasp on the prediction (a ``GraspResult``), or None
    on_prediction / on_truth : the re-grasps of the prediction and of the truth from the planned
        grasp's pre-grasp pose (``GraspResult``), or None
    reason : why there is no error value ("" when there is one)
    """

    error_deg: float | None
    per_joint_deg: np.ndarray | None = None
    planned: object | None = None
    on_prediction: object | None = None
    on_truth: object | None = None
    reason: str = ""

    @property
    def error_moving_deg(self) -> float | None:
        """Mean |Δθ| over the 6 joints that move (:data:`MOVING_JOINTS`), or None."""
        if self.per_joint_deg is None:
            return None
        return round(float(np.mean(np.asarray(self.per_joint_deg)[_MOVING])), 6)

    def as_dict(self) -> dict:
        """JSON-ready summary (angles in degrees, poses as nested lists)."""

        def plain(a):
            return None if a is None else np.asarray(a, dtype=float).round(6).tolist()

        def grasp(g):
            if g is None:
                return None
            return {
                "success": bool(g.success),
                "reason": g.reason,
                # full precision: a rotation rounded to 1e-6 is not rigid to the simulator's
                # check, and readers re-run grasps from this pose (grasps.png)
                "palm_pose": np.asarray(g.palm_pose, dtype=float).tolist(),
                "joints_deg": plain(g.joints_deg),
                "spread_deg": float(g.dofs_deg.spread),
                "epsilon": round(float(g.epsilon), 6),
                "volume": round(float(g.volume), 6),
            }

        return {
            "error_deg": self.error_deg,
            "error_moving_deg": self.error_moving_deg,
            "per_joint_deg": plain(self.per_joint_deg),
            "reason": self.reason,
            "planned": grasp(self.planned),
            "on_prediction": grasp(self.on_prediction),
            "on_truth": grasp(self.on_truth),
        }


def grasp_joint_error(
    prediction: trimesh.Trimesh | None,
    truth,
    *,
    n_candidates: int = 64,
    seed: int = 0,
    backoff: float | None = None,
    planner_options: dict | None = None,
) -> JointError:
    """Table III's grasp joint error of one completion (docs/design.md §7, Varley et al. 2017).

    prediction : the completed mesh (None when the completion is empty)
    truth : the ground-truth object mesh in the same frame (a ``trimesh.Trimesh``, or a
        :class:`grasp.hand.collision.CollisionScene` built once and reused for several predictions)

    Plan on the prediction (:func:`grasp.planner.plan`, ``n_candidates`` seeded candidates) and
    take the best grasp's palm orientation, approach line and spread. From its pre-grasp pose
    (backed off ``backoff`` metres along the approach axis, hand open) approach and autograsp
    the truth (:func:`grasp.hand.autograsp.regrasp`), and, with the very same protocol, the
    prediction. Grasping both sides from the same pre-grasp pose makes the error exactly 0 for
    identical shapes and leaves only the geometric difference; the planned grasp itself is what the
    re-grasp on the prediction reproduces whenever the approach line is clear. The planner ranks
    force-closure grasps first; when none of the candidates reaches force closure its best
    attempt is still compared (``planned.success`` is then False), as GraspIt!'s planner would
    still return its best-scoring grasp.
    """
    if prediction is None:
        return JointError(None, reason="empty completion: no surface to plan on")
    from grasp.hand.autograsp import PREGRASP_BACKOFF_M, regrasp
    from grasp.hand.collision import CollisionScene, check_mesh
    from grasp.hand.result import joint_error_deg
    from grasp.planner import plan

    back = PREGRASP_BACKOFF_M if backoff is None else float(backoff)
    scene = CollisionScene(check_mesh(prediction))  # one collision model for plan and re-grasp
    options = {"top_k": 1, **(planner_options or {})}
    grasps = plan(scene, n_candidates=n_candidates, seed=seed, **options)
    if not grasps:
        return JointError(None, reason="the planner returned no grasp on the completion")
    best = grasps[0]
    on_prediction = regrasp(best, scene, backoff=back)
    on_truth = regrasp(best, truth, backoff=back)
    mean, per_joint = joint_error_deg(on_prediction, on_truth)
    return JointError(
        error_deg=round(mean, 6),
        per_joint_deg=per_joint,
        planned=best,
        on_prediction=on_prediction,
        on_truth=on_truth,
    )
