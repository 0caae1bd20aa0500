"""A Python client of the grasp service, for robot programs.

::

    from grasp_client import GraspClient

    with GraspClient("http://127.0.0.1:8000") as client, client.session() as session:
        session.add_view(depth, K, mask=mask, camera_pose=camera_to_world)  # numpy arrays
        best = session.grasps()[0]
        robot.move(best.pregrasp_pose_world); robot.approach(best.palm_pose_world)

Depth is metres (float32/float64) or millimetres (uint16), as ROS's ``32FC1`` and ``16UC1``
images carry it; ``K`` is a 3×3 camera matrix, ROS's ``CameraInfo.k`` or ``.p``, or (fx, fy, cx,
cy). Everything is checked before a request is sent. The client raises only its own exceptions,
all :class:`ServiceError`: :class:`InvalidRequest` (a ``ValueError`` naming the field),
:class:`SessionGone`, :class:`NothingSeen`, :class:`Unauthorized`, and :class:`Unreachable` (no
answer: refused, dropped or timed out); a 503 (the service busy or full) and a refused
connection are retried with backoff, honouring ``Retry-After``, a bounded number of times.
Frames: ``*_pose`` is palm→camera of the latest view, ``*_pose_world`` palm→world when the views
came with ``camera_pose`` (docs/design.md §3, §7).
"""

from __future__ import annotations

import io
import math
import time
import uuid
from collections.abc import Mapping, Sequence
from typing import Any

import httpx
import numpy as np

from grasp_client.wire import (
    Grasp,
    SupportPlane,
    depth_f32_m,
    depth_png16_raw,
    grid_field,
    mask_png,
    object_pixels,
    rigid_pose,
)

#: ROS ``sensor_msgs/Image`` encodings of depth, and what they hold.
DEPTH_ENCODINGS = {"16UC1": "mm", "mono16": "mm", "32FC1": "m", "mm": "mm", "m": "m"}
#: The status worth another try: the service refused the request for now (planner queue full,
#: session cap) and applied nothing, so even a view can be sent again.
RETRY_STATUS = 503


class ServiceError(RuntimeError):
    """The service answered with an error; ``status`` and ``detail`` are its own (``status``
    None: the client found the problem before sending anything)."""

    def __init__(self, status: int | None, detail: Any) -> None:
        self.status, self.detail = status, detail
        super().__init__(_message(detail) if status is None else f"{status}: {_message(detail)}")


class InvalidRequest(ServiceError, ValueError):
    """422/400/413: the service refused the input; ``field`` names it (e.g. ``n_candidates``)."""

    @property
    def field(self) -> str | None:
        if isinstance(self.detail, list) and self.detail and isinstance(self.detail[0], dict):
            loc = [str(p) for p in self.detail[0].get("loc", ()) if p not in ("body", "query")]
            return ".".join(loc) or None
        return None


def _invalid(field: str, message: str) -> InvalidRequest:
    """An input the client refuses before sending it, as the service would (``field`` named)."""
    return InvalidRequest(None, [{"loc": ["body", *field.split(".")], "msg": message,
                                  "type": "value_error"}])


class Unreachable(ServiceError, ConnectionError):
    """The service could not be reached or did not answer in time (after the retries): the
    connection was refused, dropped, or timed out. A view sent when the answer timed out may
    have been stored."""


class SessionGone(ServiceError, LookupError):
    """404: the session expired, was deleted, or never existed."""


class NothingSeen(ServiceError):
    """409: no view of the session has shown the object yet, so there is nothing to grasp."""


class Unauthorized(ServiceError, PermissionError):
    """401: the service wants ``token`` (``GRASP_TOKEN``) and got none or another."""


_ERRORS = {400: InvalidRequest, 413: InvalidRequest, 422: InvalidRequest, 404: SessionGone,
           409: NothingSeen, 401: Unauthorized}


def _message(detail: Any) -> str:
    if isinstance(detail, list):
        return "; ".join(
            f"{'.'.join(str(p) for p in d.get('loc', ()))}: {d.get('msg', d)}"
            if isinstance(d, dict) else str(d) for d in detail)
    return str(detail)


class GraspClient:
    """The service at ``url``. ``retries``: further tries after a 503 or a refused connection,
    waiting ``Retry-After`` (or 0.5 s, doubling) but at most ``max_wait`` seconds each time.
    As a context manager it deletes, on exit, every session it opened that is still open."""

    def __init__(self, url: str = "http://127.0.0.1:8000", token: str | None = None, *,
                 timeout: float = 120.0, retries: int = 5, max_wait: float = 30.0,
                 transport: httpx.BaseTransport | None = None) -> None:
        if retries < 0 or not max_wait > 0:
            raise _invalid("retries", f"retries must be >= 0 and max_wait > 0, got {retries}, "
                           f"{max_wait}")
        self.url = url.rstrip("/")
        self.token = token
        self.retries, self.max_wait = retries, max_wait
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self._http = httpx.Client(base_url=self.url, headers=headers, timeout=timeout,
                                  transport=transport)
        self._open: list[Session] = []

    def session(self, support_plane: Sequence[float] | None = None, *,
                registered: bool | None = None, keep: bool = False) -> Session:
        """A new session (created on the service by its first view). ``support_plane``: the
        table the object rests on, (nx, ny, nz, d) in the world frame (n·x + d = 0, n up); it
        needs views with ``camera_pose``, is sent with the first view and kept by the session
        (the completion is cut at it, grasps treat it as an obstacle). ``registered``: whether
        the session fuses its posed views in the world frame, the object standing still (None:
        the service's default, on; False for an object that moves). ``keep``: leave the session
        on the service when the ``with`` blocks end (to open its ``inspector_url`` afterwards;
        it expires on its own, or ``delete()`` it)."""
        session = Session(self, _plane(support_plane), registered, keep)
        self._open.append(session)
        return session

    def health(self) -> dict:
        return self.request("GET", "/healthz").json()

    def request(self, method: str, path: str, **kwargs: Any) -> httpx.Response:
        """One call, retried on 503 and refused connections; errors raised as
        :class:`ServiceError` subclasses."""
        wait = 0.5
        for attempt in range(self.retries + 1):
            last = attempt == self.retries
            try:
                response = self._http.request(method, path, **kwargs)
            except (httpx.ConnectError, httpx.ConnectTimeout) as exc:  # nothing was sent: safe
                if last:  # to retry
                    raise Unreachable(None, f"no service answers at {self.url} ({exc}; tried "
                                      f"{self.retries + 1} times)") from None
                time.sleep(min(wait, self.max_wait))
                wait *= 2
                continue
            except httpx.TimeoutException as exc:
                raise Unreachable(None, f"{method} {path}: {self.url} did not answer in time "
                                  f"({exc or type(exc).__name__}); a view may have been "
                                  "stored all the same") from None
            except httpx.HTTPError as exc:  # the connection dropped mid-request, or worse
                raise Unreachable(None, f"{method} {path} to {self.url} failed: "
                                  f"{exc or type(exc).__name__}") from None
            if response.status_code == RETRY_STATUS and not last:
                time.sleep(min(_retry_after(response) or wait, self.max_wait))
                wait *= 2
                continue
            if response.status_code >= 400:
                try:
                    detail = response.json().get("detail", response.text)
                except ValueError:
                    detail = response.text
                raise _ERRORS.get(response.status_code, ServiceError)(response.status_code, detail)
            return response
        raise AssertionError("unreachable")  # pragma: no cover

    def close(self) -> None:
        """Delete the sessions still open (but those made with ``keep=True``), then close the
        connection pool."""
        for session in [s for s in self._open if not s.keep]:
            try:
                session.delete()
            except ServiceError:
                pass  # gone already, or the service is: nothing left to clean
        self._http.close()

    def __enter__(self) -> GraspClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class Session:
    """One object's views and grasps; use :meth:`GraspClient.session`. As a context manager it
    deletes itself on exit, unless made with ``keep=True``."""

    def __init__(self, client: GraspClient, support_plane: list[float] | None,
                 registered: bool | None = None, keep: bool = False) -> None:
        self.client = client
        self.keep = keep  # left on the service when the with blocks end
        self.support_plane = support_plane
        self.registered = registered  # sent with the first view: the session keeps it
        self.id: str | None = None
        self.last_reason: str | None = None  # why the last grasps() found none
        self.last_obstacle_voxels = 0  # obstacle voxels the last grasps() kept clear of

    @property
    def inspector_url(self) -> str:
        """The 3-D page of this session (with the token in the fragment, never sent to a log)."""
        self._need_id()
        token = f"#token={self.client.token}" if self.client.token else ""
        return f"{self.client.url}/sessions/{self.id}/view{token}"

    def add_view(self, depth: np.ndarray, K: Any, *, mask: np.ndarray | None = None,
                 object_label: int | None = None, camera_pose: np.ndarray | None = None,
                 encoding: str | None = None, check_frames: bool = True,
                 obstacles: bool = True, obstacle_mask: np.ndarray | None = None) -> dict:
        """Send one depth image: (H, W) or (H, W, 1) metres (float) or millimetres (uint16), 0 or
        NaN = no return; ``encoding`` a ROS name to check it against ("32FC1", "16UC1",
        "mono16"). ``K``: a 3×3 camera matrix, ROS's flat 9-number ``CameraInfo.k``, its 3×4
        ``p`` (12 numbers or 3×4), or (fx, fy, cx, cy). ``mask`` (H, W): boolean, 0/1 or 0/255
        with 0 = background, or a label image with ``object_label``, the value of the object's
        pixels. ``camera_pose`` 4×4 camera→world (OpenCV camera frame: x right, y down, z
        forward). ``check_frames=False`` skips the service's check of the pose and the support
        plane against what the view shows. With a mask, a camera pose and a support plane, the
        view's other pixels near the object (off the table) become obstacles every grasp keeps
        clear of, kept by the session (``obstacles=False``: none from this view;
        ``obstacle_mask`` (H, W), non-zero = obstacle: these pixels instead). Returns the
        service's answer (``view_index``, ``observed_voxels``, ``occupied_voxels``, and
        ``completion``: "registered" when posed views were fused, else "memory")."""
        depth = _squeeze(depth, "depth")
        body = {"depth": _depth_field(depth, encoding), "intrinsics": _intrinsics(K)}
        if mask is not None:
            body["mask"] = mask_png(_object_pixels(_squeeze(mask, "mask"), np.shape(depth),
                                                   object_label))
        elif object_label is not None:
            raise _invalid("object_label", "object_label names the object's value in a label "
                           "image: it needs mask")
        if not obstacles:
            body["obstacles"] = False
        elif obstacle_mask is not None:
            others = np.asarray(_squeeze(obstacle_mask, "obstacle_mask"))
            if others.shape != np.shape(depth):
                raise _invalid("obstacle_mask", f"obstacle_mask is {others.shape}, the depth "
                               f"image {np.shape(depth)}: give one of the image's size")
            body["obstacle_mask"] = mask_png(others != 0)
        return self._post(body, camera_pose, check_frames)

    def add_points(self, points: np.ndarray, *, camera_pose: np.ndarray | None = None,
                   check_frames: bool = True) -> dict:
        """Send the object's observed points, (N, 3) metres in the camera frame."""
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
            raise _invalid("points",
                           f"points must be a finite (N, 3) array, got shape {p.shape}")
        return self._post({"points": p.tolist()}, camera_pose, check_frames)

    def add_grid(self, grid, *, camera_pose: np.ndarray | None = None,
                 check_frames: bool = True) -> dict:
        """Send a ready 40³ grid: an object with ``pack()`` (the 8000 packed bytes) and
        ``grid_to_camera``, such as the service's ``completion.grid.VoxelGrid``."""
        return self._post({"grid": grid_field(grid)}, camera_pose, check_frames)

    def grasps(self, top_k: int = 1, *, n_candidates: int | None = None,
               verify: int | None = None, min_hold: float | None = None) -> list[Grasp]:
        """The best ``top_k`` distinct grasps of the current completion, best first; an empty
        list when no candidate held (``last_reason`` says why). ``verify``: lift-test at most
        this many of the best on the completion first (each grasp's ``verification`` says what
        its trials saw; default: the service's). ``min_hold``: on a table, return force-closure
        grasps down to this hold probability (default: the service's 0.5) to decide yourself."""
        self._need_id()
        params: dict[str, Any] = {"session_id": self.id, "top_k": int(top_k)}
        if n_candidates is not None:
            params["n_candidates"] = int(n_candidates)
        if verify is not None:
            params["verify"] = int(verify)
        if min_hold is not None:
            params["min_hold"] = float(min_hold)
        out = self.client.request("GET", "/grasp", params=params).json()
        self.last_reason = out.get("reason")
        self.last_obstacle_voxels = int(out.get("obstacle_voxels", 0))
        return [Grasp.from_json(g) for g in out["grasps"]]

    def mesh(self):
        """The completion as a ``trimesh.Trimesh`` in the latest view's camera frame (metres);
        needs trimesh, which the client does not install (:meth:`mesh_ply` needs nothing)."""
        import trimesh

        return trimesh.load(io.BytesIO(self.mesh_ply()), file_type="ply", force="mesh")

    def mesh_ply(self) -> bytes:
        """The completion as binary PLY bytes, the latest view's camera frame (metres)."""
        self._need_id()
        return self.client.request("GET", f"/sessions/{self.id}/mesh",
                                   params={"format": "ply"}).content

    def info(self) -> dict:
        """``GET /sessions/{id}``: views, whether the object was seen, expiry, the support
        plane it keeps."""
        self._need_id()
        return self.client.request("GET", f"/sessions/{self.id}").json()

    def delete(self) -> None:
        if self.id is not None:
            try:
                self.client.request("DELETE", f"/sessions/{self.id}")
            except SessionGone:
                pass
        if self in self.client._open:
            self.client._open.remove(self)
        self.id = None

    def _post(self, body: dict, camera_pose: np.ndarray | None, check_frames: bool) -> dict:
        if not check_frames:
            body["check_frames"] = False
        if camera_pose is not None:
            try:
                body["camera_pose"] = rigid_pose(camera_pose).tolist()
            except ValueError as exc:
                raise _invalid("camera_pose", str(exc)) from None
        if self.id is not None:
            body["session_id"] = self.id
        else:  # the session keeps these from its first view
            if self.support_plane is not None:
                body["support_plane"] = self.support_plane
            if self.registered is not None:
                body["registered"] = self.registered
        # one key per view, the same on every retry: a view whose answer was lost is not applied
        # twice (the service keeps the first answer under it)
        key = {"Idempotency-Key": uuid.uuid4().hex}
        out = self.client.request("POST", "/views", json=body, headers=key).json()
        self.id = out["session_id"]
        return out

    def _need_id(self) -> None:
        if self.id is None:
            raise NothingSeen(None, "the session has no view yet: add_view, add_points or "
                              "add_grid first")

    def __enter__(self) -> Session:
        return self

    def __exit__(self, *exc: object) -> None:
        if not self.keep:
            self.delete()


def _depth_field(depth: np.ndarray, encoding: str | None) -> dict:
    d = np.asarray(depth)
    if d.ndim != 2 or min(d.shape) < 1:
        raise _invalid("depth", f"depth must be an (H, W) image, got shape {d.shape}")
    unit = "mm" if d.dtype == np.uint16 else "m" if d.dtype.kind == "f" else None
    if unit is None:
        raise _invalid("depth", f"depth must be float metres or uint16 millimetres, got {d.dtype}")
    if encoding is not None:
        if encoding not in DEPTH_ENCODINGS:
            raise _invalid("depth.encoding",
                           f"encoding must be one of {sorted(DEPTH_ENCODINGS)}, got {encoding!r}")
        if DEPTH_ENCODINGS[encoding] != unit:
            raise _invalid("depth.encoding",
                           f"encoding {encoding!r} holds {DEPTH_ENCODINGS[encoding]} but the "
                             f"depth array is {d.dtype} ({unit})")
    return depth_png16_raw(d) if unit == "mm" else depth_f32_m(d)


def _squeeze(image: Any, name: str) -> np.ndarray:
    """An (H, W, 1) image (as ROS image arrays often come) as (H, W)."""
    a = np.asarray(image)
    return a[..., 0] if a.ndim == 3 and a.shape[2] == 1 else a


def _object_pixels(mask: Any, shape: tuple[int, ...], label: int | None) -> np.ndarray:
    """(H, W) bool: the object's pixels by the service's own rule (:func:`object_pixels`)."""
    m = np.asarray(mask)
    if m.shape != tuple(shape):
        raise _invalid("mask", f"mask must have the depth image's shape {tuple(shape)}, "
                       f"got {m.shape}")
    try:
        return object_pixels(m, label)
    except ValueError as exc:
        raise _invalid("mask", str(exc)) from None


def _intrinsics(K: Any) -> dict:
    """fx, fy, cx, cy from a 3×3 camera matrix, four numbers, or a mapping with those keys."""
    if isinstance(K, Mapping):
        values = [K.get(k) for k in ("fx", "fy", "cx", "cy")]
    else:
        k = np.asarray(K, dtype=np.float64)
        if k.shape in ((9,), (12,)):  # ROS CameraInfo.k (3×3) or .p (3×4), row-major
            k = k.reshape(3, -1)
        if k.shape == (3, 4):  # a projection matrix P = K [I | t]: its left 3×3 is K
            if not np.allclose(k[2], [0, 0, 1, 0]):
                raise _invalid("intrinsics", "a 3×4 P must end in the row [0, 0, 1, 0] "
                               f"(ROS CameraInfo.p), got {k[2].tolist()}")
            k = k[:, :3]
        if k.shape == (3, 3):
            if not np.allclose(k[2], [0, 0, 1]) or k[0, 1] != 0 or k[1, 0] != 0:
                raise _invalid("intrinsics",
                               "K must be a pinhole camera matrix [[fx, 0, cx], [0, fy, cy], "
                                 f"[0, 0, 1]], got {k.tolist()}")
            values = [k[0, 0], k[1, 1], k[0, 2], k[1, 2]]
        elif k.shape == (4,):
            values = list(k)
        else:
            raise _invalid("intrinsics", "K must be 3×3, 9 or 12 numbers (ROS CameraInfo.k or .p), "
                           f"3×4 or (fx, fy, cx, cy), got shape {k.shape}")
    if any(v is None for v in values):
        raise _invalid("intrinsics", "K needs fx, fy, cx and cy")
    fx, fy, cx, cy = (float(v) for v in values)
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or fx <= 0 or fy <= 0:
        raise _invalid("intrinsics",
                       f"K needs finite fx, fy > 0 and finite cx, cy; got {fx}, {fy}, {cx}, {cy}")
    return {"fx": fx, "fy": fy, "cx": cx, "cy": cy}


def _plane(plane: Sequence[float] | None) -> list[float] | None:
    if plane is None:
        return None
    try:
        return SupportPlane.from_values(plane).as_array().tolist()
    except ValueError as exc:
        raise _invalid("support_plane", str(exc)) from None


def _retry_after(response: httpx.Response) -> float | None:
    """Seconds from a ``Retry-After`` header given in seconds (dates are ignored)."""
    try:
        seconds = float(response.headers.get("retry-after", ""))
    except ValueError:
        return None
    return seconds if math.isfinite(seconds) and seconds >= 0 else None
