"""The chain behind the routes, as plain blocking functions (the app runs them in worker threads).

``POST /views``: stored state → ``CompletionStream`` step → stored state.
``GET /grasp``: stored state → completion → mesh (marching cubes); :mod:`service.engine.planning`
plans.

A view to an existing session is applied while its caller holds the session's lock across
replicas (:meth:`service.store.base.Store.try_lock`, which never waits: the app waits for it on its
event loop, not in an inference slot, see :meth:`service.services.Services.exclusive`); the
compare-and-swap on the view count is what guarantees each view is applied once and in order.
"""

from __future__ import annotations

import copy
import hashlib
import time
import uuid
from dataclasses import dataclass

import numpy as np
import torch
import trimesh

from completion.grid import VoxelGrid, transform_points
from completion.mesh import grid_to_mesh
from completion.stream import Completion, CompletionStream, ViewResult
from grasp.search.obstacles import seen_others
from grasp_client.wire import SupportPlane
from service.intake.frames import FrameChecks, Previous, check_plane, check_view
from service.intake.inputs import DecodedView, InputError
from service.store.base import ConcurrentUpdate, SessionRecord, Store
from service.store.owned import OwnedStore

#: How often a view is re-applied when another process changed the session meanwhile.
UPDATE_ATTEMPTS = 5


class ModelMismatch(RuntimeError):
    """A stored session was made by a different model than the one this server runs."""


class TooManyViews(RuntimeError):
    """The session holds as many views as a model whose state grows with them may keep."""


def model_fingerprint(model: torch.nn.Module) -> str:
    """A short hash of the weights: a stored state only fits the model that made it."""
    digest = hashlib.sha256()
    for name, tensor in sorted(model.state_dict().items()):
        digest.update(name.encode())
        digest.update(tensor.detach().cpu().contiguous().numpy().tobytes())
    return digest.hexdigest()[:16]


@dataclass(frozen=True)
class Snapshot:
    """A session's completion at one moment, with the camera pose of its latest view and that
    view's observed voxel centres (n, 3) in the same camera frame: one consistent state."""

    record: SessionRecord
    completion: Completion
    camera_to_world: np.ndarray | None  # (4, 4) of the latest view, when given
    observed: np.ndarray  # (n, 3) the latest view's observed voxel centres
    support_plane: SupportPlane | None = None  # world frame, when the session keeps one
    obstacles: np.ndarray | None = None  # (k, 3) obstacle voxel centres, the same camera frame


class Pipeline:
    """One loaded model and the session store; every method is blocking and thread-safe."""

    def __init__(
        self,
        model: torch.nn.Module,
        store: Store,
        *,
        model_name: str,
        max_views: int | None = None,
        frame_checks: FrameChecks | None,
        registered: bool = True,
        posed_model: torch.nn.Module | None = None,
    ) -> None:
        self.model = model.eval()
        self.store = store
        self.model_name = model_name
        # a stored state fits the weights that made it: with a posed model, both
        self.model_id = model_fingerprint(model)
        if posed_model is not None:
            self.model_id = model_fingerprint(posed_model)[:8] + self.model_id[:8]
        #: what a registered session whose first view has a camera pose runs (``mvp_posed``)
        self.posed_model = None if posed_model is None else posed_model.eval()
        # only a model whose state grows with every view (MVT's key/value cache) is capped
        grows = getattr(getattr(model, "config", None), "kind", "") == "mvt"
        self.max_views = max_views if grows else None
        self.frame_checks = frame_checks  # None: views' frames are not checked
        self.registered = registered  # a new session fuses its posed views (completion.evidence)

    def for_owner(self, owner: str) -> Pipeline:
        """This pipeline on the sessions of the client ``owner`` alone
        (:class:`service.store.owned.OwnedStore`): what every route with a session runs."""
        owned = copy.copy(self)
        owned.store = OwnedStore(self.store, owner)
        return owned

    # ---------------------------------------------------------------------------- views
    def add_view(self, session_id: str | None, view: DecodedView) -> tuple[str, ViewResult]:
        """Apply one view (to a new session when ``session_id`` is None) and store the state.

        For an existing session the caller holds its lock (``store.try_lock``); without it a view
        that another replica applied first is applied again on top (up to ``UPDATE_ATTEMPTS``).
        """
        if session_id is None:
            self.store.ensure_room()
            stream = CompletionStream(self.model, registered=self.registered,
                                      posed_model=self.posed_model)
            self._check(stream, view)
            result = _step(stream, view)
            _keep_obstacles(stream, view)
            session_id = uuid.uuid4().hex
            self.store.create(
                session_id,
                model=self.model_id,
                state=stream.to_bytes(),
                views=stream.views,
                object_seen=stream.seen,
            )
            return session_id, result
        return session_id, self._apply(session_id, view)

    def _apply(self, session_id: str, view: DecodedView) -> ViewResult:
        for _ in range(UPDATE_ATTEMPTS):
            record = self.store.get(session_id)
            if self.max_views is not None and record.views >= self.max_views:
                raise TooManyViews(
                    f"session {session_id!r} has {record.views} views, the most a "
                    f"{self.model_name!r} session keeps (its state grows with every view; "
                    "GRASP_MAX_VIEWS): start a new session"
                )
            stream = self._stream(record)
            self._check(stream, view)
            result = _step(stream, view)
            _keep_obstacles(stream, view)
            try:
                self.store.update(
                    record,
                    state=stream.to_bytes(),
                    views=stream.views,
                    object_seen=stream.seen,
                )
            except ConcurrentUpdate:
                continue  # another process applied a view first: apply ours on top of it
            return result
        raise ConcurrentUpdate(
            f"session {session_id!r} kept changing while this view was applied; send it again"
        )

    def _check(self, stream: CompletionStream, view: DecodedView) -> None:
        """The view's camera pose and support plane against what it and the session show
        (:mod:`service.intake.frames`); raises InputError."""
        if self.frame_checks is None or not view.check_frames:
            return
        plane = view.support_plane if view.support_plane is not None else stream.support_plane
        previous = None
        if stream.camera_to_world is not None and stream.seen:
            seen = stream.observed_points()
            previous = Previous(stream.camera_to_world,
                                transform_points(seen, stream.camera_to_world))
        check_view(view, plane, previous, self.frame_checks)

    def _stream(self, record: SessionRecord) -> CompletionStream:
        if record.model != self.model_id:
            raise ModelMismatch(
                f"session {record.id!r} was made by another model (weights {record.model}); this "
                f"server runs {self.model_name!r} (weights {self.model_id}): start a new session"
            )
        return CompletionStream.from_bytes(self.model, record.state, posed_model=self.posed_model)

    def _keep_plane(self, record: SessionRecord, stream: CompletionStream,
                    plane: SupportPlane) -> None:
        """Keep ``plane`` (world frame) with the session from now on (the caller holds its lock,
        as for a view); nothing is written when the session already keeps the same plane.
        Raises ConcurrentUpdate when another process changed the session meanwhile."""
        before = stream.support_plane
        if self.frame_checks is not None and stream.seen and stream.camera_to_world is not None:
            check_plane(plane, stream.observed_points(), stream.camera_to_world,
                        self.frame_checks)  # a refused plane: nothing stored changes
        try:
            stream.set_support_plane(plane)
        except ValueError as exc:  # no camera poses
            raise InputError(("query", "support_plane"), str(exc)) from exc
        if before is not None and np.allclose(before.as_array(), plane.as_array(), atol=1e-12):
            return
        self.store.update(record, state=stream.to_bytes(), views=stream.views,
                          object_seen=stream.seen)

    # ---------------------------------------------------------------------------- outputs
    def _read(self, session_id: str,
              support_plane: SupportPlane | None = None) -> tuple[SessionRecord, CompletionStream]:
        """The session's record and stream, read once; with ``support_plane`` (world frame) the
        session keeps that plane from now on (the caller holds its lock, as for a view), read
        again when another process changed it meanwhile (up to ``UPDATE_ATTEMPTS``)."""
        for _ in range(UPDATE_ATTEMPTS):
            record = self.store.get(session_id)
            stream = self._stream(record)
            try:
                if support_plane is not None:
                    self._keep_plane(record, stream, support_plane)
                return record, stream
            except ConcurrentUpdate:
                continue
        raise ConcurrentUpdate(
            f"session {session_id!r} kept changing while its support plane was stored; retry"
        )

    def snapshot(self, session_id: str) -> Snapshot:
        """The latest completion; raises NoObjectError before any view with object points."""
        record, stream = self._read(session_id)
        return _snapshot(record, stream, stream.completion())

    def occupancy(self, session_id: str) -> tuple[Snapshot, VoxelGrid]:
        snap = self.snapshot(session_id)
        return snap, snap.completion.voxel_grid()

    def mesh(self, session_id: str) -> trimesh.Trimesh:
        """Mesh of the latest completion (camera frame); raises EmptyMeshError if empty."""
        c = self.snapshot(session_id).completion
        return grid_to_mesh(c.probabilities, c.grid_to_camera, threshold=c.threshold)

    def grasp_mesh(
        self, session_id: str, support_plane: SupportPlane | None = None
    ) -> tuple[Snapshot, trimesh.Trimesh, dict[str, float]]:
        """What ``GET /grasp`` plans on: the completion's mesh; and each stage's milliseconds.
        The session is read once (:meth:`_read`: with ``support_plane`` it keeps that plane, and
        the completion is cut at it)."""
        t0 = time.perf_counter()
        record, stream = self._read(session_id, support_plane)
        t1 = time.perf_counter()
        completion = stream.completion()
        t2 = time.perf_counter()
        mesh = grid_to_mesh(
            completion.probabilities, completion.grid_to_camera, threshold=completion.threshold
        )
        t3 = time.perf_counter()
        timing = {"load": t1 - t0, "completion": t2 - t1, "mesh": t3 - t2}
        snapshot = _snapshot(record, stream, completion)
        return snapshot, mesh, {k: v * 1e3 for k, v in timing.items()}


def _snapshot(record: SessionRecord, stream: CompletionStream, completion: Completion) -> Snapshot:
    obstacles = None  # kept in the world frame: a session with any has camera poses
    if len(stream.obstacle_keys):
        obstacles = transform_points(stream.obstacle_points(),
                                     np.linalg.inv(stream.camera_to_world))
    return Snapshot(record, completion, stream.camera_to_world, stream.observed_points(),
                    stream.support_plane, obstacles)


def _keep_obstacles(stream: CompletionStream, view: DecodedView) -> None:
    """Keep the view's other pixels that are obstacles (:func:`grasp.search.obstacles.seen_others`)
    with the session, world frame: a view with a camera pose, in a session with a table."""
    if (view.others is None or view.camera_to_world is None or stream.support_plane is None
            or not len(view.others) or view.points is None or not len(view.points)):
        return
    pose = view.camera_to_world
    kept = seen_others(transform_points(view.others, pose), transform_points(view.points, pose),
                       stream.support_plane)
    if len(kept):
        stream.add_obstacles(kept)


def _step(stream: CompletionStream, view: DecodedView) -> ViewResult:
    if view.registered is not None:  # the session's choice, from this view on
        stream.registered = view.registered
    try:
        return stream.add_view(view)
    except ValueError as exc:  # the stream's own checks on the decoded arrays
        raise InputError(("body",), str(exc)) from exc
