"""``CompletionStream``: feed views one at a time into a loaded model, get the completion.

Each view, given as a depth image + intrinsics (+ mask), a camera-frame point cloud or a ready
grid, is voxelized in its own grid exactly as training did (docs/design.md §3: the Varley fit on the
view's points, or, while the camera has not moved (a view with the same camera pose as the one
before), on every point seen from that pose; a view with no object points keeps the previous
view's grid, re-expressed in the new camera frame when both views came with camera poses: one
rule with the training data, :func:`completion.grid.view_grid`),
the model takes one streaming step, and the completion is the model's output for the latest
view: occupancy probabilities (40, 40, 40) with the grid's ``grid_to_camera`` (the latest view's
camera frame). A stream counts as having seen the object only after a view with at least one
observed voxel; before that it reports 0 occupied voxels and has no completion.

A support plane (the table the object rests on, a :class:`grasp_client.wire.SupportPlane` in the
world frame, :meth:`CompletionStream.set_support_plane`) cuts the completion: every voxel whose
centre lies below it is empty in :meth:`CompletionStream.completion`, so meshing, planning and
every output see nothing under the table. The views then need their camera poses (the plane is
in the world frame, the grid in the latest camera's).

When the views come with camera poses, the stream also keeps :mod:`completion.evidence`: the
object taken as still, every posed view's logits are carried into one constant-size world grid,
and a view's completion is its own logits averaged there with every earlier view's
(``registered``, on by default; :attr:`CompletionStream.fused` says whether the latest completion
came this way). Views without poses take MVP's answer alone, exactly as before the evidence
existed; a moving object needs ``registered=False``.

What else the views showed near the object (the neighbours on a table) a service may keep with
the stream as obstacle voxels in the world frame (:meth:`CompletionStream.add_obstacles`); the
completion does not use them.

The whole stream state (model memory, current grid, latest logits, counters, the plane, the
obstacles, the registered evidence) serialises to bytes and back exactly, so a service can persist
a session after every view.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np
import torch

from completion import evidence as E
from completion import grid as G
from completion.view import PLANE_NEEDS_POSE, View
from grasp_client.wire import SupportPlane

DEFAULT_THRESHOLD = 0.5
#: The other objects a session's views showed (obstacles to the planner,
#: :mod:`grasp.search.obstacles`) are kept as world-frame voxels of
#: :data:`completion.grid.OBSTACLE_PITCH_M`, at most this many (the nearest to the object's latest
#: seen points are kept).
MAX_OBSTACLE_VOXELS = 50_000


class NoObjectError(ValueError):
    """Raised when a completion is asked for before any view showed object points (a session
    counts as seen only after a view with at least one observed voxel)."""


@dataclass(frozen=True)
class ViewResult:
    view_index: int  # 0-based index of this view in the stream
    observed_voxels: int  # occupied voxels of this view's input grid
    occupied_voxels: int  # voxels of the completion above the threshold
    registered: bool = False  # the completion averaged posed views (completion.evidence)


@dataclass(frozen=True)
class Completion:
    probabilities: np.ndarray  # (40, 40, 40) float32 in [0, 1]
    grid_to_camera: np.ndarray  # (4, 4) float64, latest view's camera frame
    threshold: float
    views: int

    @property
    def occupancy(self) -> np.ndarray:
        """(40, 40, 40) bool at the decision threshold."""
        return self.probabilities >= self.threshold

    def voxel_grid(self) -> G.VoxelGrid:
        return G.VoxelGrid(self.occupancy, self.grid_to_camera)


class CompletionStream:
    """Streaming completion with one loaded model (not thread-safe: one stream per session)."""

    def __init__(self, model: torch.nn.Module, *, threshold: float | None = None,
                 registered: bool = True, posed_model: torch.nn.Module | None = None) -> None:
        self.model = model.eval()
        #: fuse posed views in the world frame (:mod:`completion.evidence`; a still object)
        self.registered = registered
        #: a ``registered_input`` model (``mvp_posed``): a registered stream whose first view
        #: comes with its camera pose runs it instead of ``model``, fed the surface earlier views
        #: saw (:meth:`completion.evidence.RegisteredEvidence.seen`)
        self.posed_model = None if posed_model is None else posed_model.eval()
        if posed_model is not None and not posed_model.config.registered_input:
            raise ValueError("posed_model must take the registered surface (registered_input)")
        self.on_posed = False  # this stream's memory and completions are the posed model's
        self.fused = False  # the latest completion is the registered one
        self._evidence: E.RegisteredEvidence | None = None
        self.threshold = float(
            threshold if threshold is not None else getattr(model, "threshold", DEFAULT_THRESHOLD)
        )
        self.views = 0
        self.seen = False  # a view with at least one observed voxel has come
        self.grid_to_camera: np.ndarray | None = None
        self.camera_to_world: np.ndarray | None = None
        self._seen_bounds: np.ndarray | None = None  # of the points seen from this pose
        self._state = model.init_state(1)
        self._logits: np.ndarray | None = None
        self._observed: np.ndarray | None = None  # the latest view's input grid (bool)
        # what else the views showed near the object: (n, 3) int32 world voxel keys
        self.obstacle_keys = np.zeros((0, 3), dtype=np.int32)
        self.support_plane: SupportPlane | None = None  # world frame

    def set_support_plane(self, plane: SupportPlane) -> None:
        """Cut every completion at this plane (world frame) from now on. ValueError when the
        latest view came without a camera pose (the plane could not be placed in its frame)."""
        if self.views and self.camera_to_world is None:
            raise ValueError(f"{SupportPlane.NEEDS_POSES} (the latest view came without one)")
        self.support_plane = plane

    # ------------------------------------------------------------------ input
    def add_view(self, view: View | None = None, /, **given) -> ViewResult:
        """Add one view: a :class:`completion.view.View`, or its parts as keywords, checked by
        :meth:`View.of` (exactly one of ``depth`` with ``intrinsics`` and ``mask``, ``points`` or
        ``grid``; ``camera_to_world``; ``support_plane``). A view's ``support_plane`` (world
        frame) is kept from this view on, as :meth:`set_support_plane` would, and already cuts
        this view's completion; once the stream keeps a plane every view needs its pose."""
        if view is None:
            view = View.of(**given)
        elif given:
            raise TypeError("give a View or its parts as keywords, not both")
        pose = view.camera_to_world
        if pose is None and self.support_plane is not None:
            raise ValueError(PLANE_NEEDS_POSE)
        if view.support_plane is not None:
            self.support_plane = view.support_plane
        bounds = None
        if view.grid is None:
            pts = view.points
            assert pts.ndim == 2 and pts.shape[1] == 3 and pts.dtype == np.float64
            transform, bounds = G.view_grid(
                pts, pose, self.grid_to_camera, self.camera_to_world, self._seen_bounds
            )
            occ = (
                G.voxelize_points(pts, transform)
                if transform is not None
                else np.zeros(G.GRID_SHAPE, dtype=bool)
            )
        else:
            transform, occ = view.grid.grid_to_camera, view.grid.occupancy
        result = self._step(occ, transform, pose)
        self._seen_bounds = bounds
        return result

    def add_obstacles(self, points: np.ndarray) -> int:
        """Keep ``points`` (world frame, (m, 3)) as obstacle voxels (:func:`G.voxel_keys`)
        with those kept before (at most :data:`MAX_OBSTACLE_VOXELS`: the nearest to the object's
        latest seen points); how many are kept now."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        keys = G.voxel_keys(points, G.OBSTACLE_PITCH_M).astype(np.int32)
        keys = np.unique(np.concatenate([self.obstacle_keys, keys]), axis=0)
        if len(keys) > MAX_OBSTACLE_VOXELS:
            centre = np.zeros(3)
            if self.seen and self.camera_to_world is not None:
                centre = G.transform_points(self.observed_points(), self.camera_to_world).mean(0)
            distance = np.linalg.norm(self._centres(keys) - centre, axis=1)
            keys = keys[np.sort(np.argsort(distance, kind="stable")[:MAX_OBSTACLE_VOXELS])]
        self.obstacle_keys = keys.astype(np.int32)
        return len(keys)

    def obstacle_points(self) -> np.ndarray:
        """The obstacle voxels' centres (n, 3), world frame."""
        return self._centres(self.obstacle_keys)

    @staticmethod
    def _centres(keys: np.ndarray) -> np.ndarray:
        return (keys + 0.5) * G.OBSTACLE_PITCH_M

    def _step(self, occ: np.ndarray, transform, camera_to_world) -> ViewResult:
        frame = torch.from_numpy(np.ascontiguousarray(occ, dtype=np.float32))[None]
        posed = self.registered and camera_to_world is not None and transform is not None
        if self.views == 0 and posed and self.posed_model is not None:
            self.on_posed = True  # decided by the first view: the memory is one model's
        with torch.no_grad():
            if self.on_posed:
                seen = np.zeros(G.GRID_SHAPE, dtype=np.float32)
                if posed and self._evidence is not None:
                    seen = self._evidence.seen(transform, camera_to_world).astype(np.float32)
                logits, self._state = self.posed_model.step(
                    self._state, frame, seen=torch.from_numpy(seen)[None])
            else:
                logits, self._state = self.model.step(self._state, frame)
        self._logits = logits[0].float().numpy()
        index = self.views
        self.views += 1
        observed = int(occ.sum())
        self.fused = False
        if posed:
            self._logits = self._fuse(self._logits, occ, transform, camera_to_world)
        self.seen = self.seen or observed > 0
        self._observed = np.asarray(occ, dtype=bool)
        self.grid_to_camera = transform
        self.camera_to_world = camera_to_world
        occupied = 0
        if self.seen:
            above = self._logits >= _logit(self.threshold)
            below = self._below_plane()
            occupied = int((above if below is None else above & ~below).sum())
        return ViewResult(index, observed, occupied, self.fused)

    def _fuse(self, logits: np.ndarray, occ: np.ndarray, transform: np.ndarray,
              camera_to_world: np.ndarray) -> np.ndarray:
        """A posed view's logits averaged with the registered evidence, which they and the view's
        observed surface then join (a view without object points only reads it: an empty input's
        answer says nothing)."""
        has_points = bool(occ.any())
        if self._evidence is None:
            if not has_points:
                return logits
            self._evidence = E.RegisteredEvidence.around(transform, camera_to_world)
        fused = self._evidence.fuse(logits, transform, camera_to_world, own=has_points)
        if has_points:
            self._evidence.add(logits, transform, camera_to_world)
            self._evidence.add_surface(occ, transform, camera_to_world)
        self.fused = True
        return fused.astype(np.float16).astype(np.float32)  # as stored: restored, the same

    def _below_plane(self) -> np.ndarray | None:
        """(40, 40, 40) bool: the current grid's voxels below the support plane (None: no plane
        or no grid)."""
        if self.support_plane is None or self.grid_to_camera is None:
            return None
        plane = self.support_plane.transformed(self.camera_to_world)
        return G.voxels_below_plane(self.grid_to_camera, plane)

    # ------------------------------------------------------------------ output
    def completion(self) -> Completion:
        """The latest view's completion; raises NoObjectError before any object points."""
        if not self.seen or self._logits is None or self.grid_to_camera is None:
            raise NoObjectError("no view with object points has been added yet")
        probs = (1.0 / (1.0 + np.exp(-self._logits.astype(np.float64)))).astype(np.float32)
        below = self._below_plane()
        if below is not None:
            probs[below] = 0.0  # nothing under the table
        return Completion(probs, self.grid_to_camera.copy(), self.threshold, self.views)

    @property
    def logits(self) -> np.ndarray:
        """(40, 40, 40) float32: the latest view's logits in its grid (registered when
        :attr:`fused`), before any cut; ValueError before any view."""
        if self._logits is None:
            raise ValueError("no view has been added yet")
        return self._logits.copy()

    def observed_points(self) -> np.ndarray:
        """(n, 3) centres of the latest view's observed voxels, in its camera frame (the frame
        of :meth:`completion`); empty before any view."""
        if self._observed is None or self.grid_to_camera is None:
            return np.zeros((0, 3))
        return G.VoxelGrid(self._observed, self.grid_to_camera).points()

    # ------------------------------------------------------------------ persistence
    def to_bytes(self) -> bytes:
        """The whole stream state; :meth:`from_bytes` restores it exactly."""
        from completion.model import state_to_bytes

        buf = io.BytesIO()
        arrays = {
            "model_state": np.frombuffer(state_to_bytes(self._state), dtype=np.uint8),
            "views": np.array(self.views),
            "seen": np.array(self.seen),
            "threshold": np.array(self.threshold),
        }
        if self.grid_to_camera is not None:
            arrays["grid_to_camera"] = self.grid_to_camera
        if self.camera_to_world is not None:
            arrays["camera_to_world"] = self.camera_to_world
        if self._logits is not None and self.fused:  # float16: the state stays under 400 kB
            arrays["fused_logits"] = self._logits.astype(np.float16)
        elif self._logits is not None:
            arrays["logits"] = self._logits
        if self._evidence is not None:
            arrays.update(self._evidence.to_arrays("evidence_"))
        if not self.registered:
            arrays["registered"] = np.array(False)
        if self.on_posed:
            arrays["posed_model"] = np.array(True)
        if self._seen_bounds is not None:
            arrays["seen_bounds"] = self._seen_bounds
        if self._observed is not None:
            arrays["observed"] = np.packbits(self._observed.reshape(-1))
        if self.support_plane is not None:
            arrays["support_plane"] = self.support_plane.as_array()
        if len(self.obstacle_keys):  # as bits of their box, deflated: ~30 kB at the cap
            arrays["obstacles_packed"] = G.pack_voxel_keys(self.obstacle_keys)
        np.savez(buf, **arrays)
        return buf.getvalue()

    @classmethod
    def from_bytes(cls, model: torch.nn.Module, data: bytes, *,
                   posed_model: torch.nn.Module | None = None) -> CompletionStream:
        """The stream :meth:`to_bytes` stored, with the models it was made with (ValueError when
        it ran ``posed_model`` and none is given)."""
        from completion.model import state_from_bytes

        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            stream = cls(model, threshold=float(z["threshold"]), posed_model=posed_model)
            stream.on_posed = "posed_model" in z and bool(z["posed_model"])
            if stream.on_posed and posed_model is None:
                raise ValueError("this stream ran the posed model (mvp_posed); give posed_model")
            stream._state = state_from_bytes(z["model_state"].tobytes())
            stream.views = int(z["views"])
            stream.grid_to_camera = z["grid_to_camera"] if "grid_to_camera" in z else None
            stream.camera_to_world = z["camera_to_world"] if "camera_to_world" in z else None
            stream._logits = z["logits"] if "logits" in z else None
            if "fused_logits" in z:
                stream._logits, stream.fused = z["fused_logits"].astype(np.float32), True
            stream._evidence = E.RegisteredEvidence.from_arrays(z, "evidence_")
            stream.registered = bool(z["registered"]) if "registered" in z else True
            stream._seen_bounds = z["seen_bounds"] if "seen_bounds" in z else None
            if "observed" in z:
                stream._observed = G.VoxelGrid.unpack(z["observed"].tobytes())
            stream.support_plane = _plane(z)
            if "obstacles_packed" in z:
                stream.obstacle_keys = G.unpack_voxel_keys(z["obstacles_packed"])
            elif "obstacle_keys" in z:  # states stored before obstacles were packed
                stream.obstacle_keys = z["obstacle_keys"]
            # states stored before "seen" existed: seen once a grid was fitted
            stream.seen = bool(z["seen"]) if "seen" in z else stream.grid_to_camera is not None
        return stream


def stored_support_plane(data: bytes) -> SupportPlane | None:
    """The support plane (world frame) kept in a stream state (:meth:`CompletionStream.to_bytes`),
    read without a model; None when the stream has none."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return _plane(z)


def stored_registration(data: bytes) -> tuple[bool, bool]:
    """(whether the stream fuses posed views, whether its latest completion did), read from a
    stream state (:meth:`CompletionStream.to_bytes`) without a model."""
    with np.load(io.BytesIO(data), allow_pickle=False) as z:
        return (bool(z["registered"]) if "registered" in z else True), "fused_logits" in z


def _plane(arrays) -> SupportPlane | None:
    """The stored plane of a loaded state (checked again: the bytes came from storage)."""
    return SupportPlane.from_values(arrays["support_plane"]) if "support_plane" in arrays else None


def _logit(p: float) -> float:
    p = min(max(p, 1e-7), 1 - 1e-7)
    return float(np.log(p / (1 - p)))
