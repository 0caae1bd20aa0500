"""What travels between a robot program and the grasp service, defined once.

The client builds and reads these; the service (``service/api/schemas.py``) uses the same classes as
its request and response bodies, so the OpenAPI schema comes from here. Only numpy is needed:
the annotations below carry hooks (``__get_pydantic_core_schema__``) that pydantic calls on the
server and that nothing calls on a robot PC.

- :class:`Grasp`, :class:`Contact`, :class:`Primitive`: one planned grasp (``GET /grasp``).
- :class:`SupportPlane`: the table, ``[nx, ny, nz, d]`` (n·x + d = 0, n up), checked and parsed
  here only.
- :func:`rigid_pose`: a camera→world pose's checks; :data:`Pose`, :data:`RigidPose` its field.
- :func:`object_pixels`: the mask rule (boolean, 0/1, 0/255, or a label image with its label).
- :func:`png_bytes`, :func:`depth_png16_mm`, :func:`depth_f32_m`, :func:`mask_png`: the body's
  encodings of depth images and masks.

Frames (docs/design.md §3, §7): camera frames are OpenCV optical (x right, y down, z forward,
metres); ``*_pose`` is palm→camera of the latest view, ``*_pose_world`` palm→world.
"""

from __future__ import annotations

import base64
import math
import re
import struct
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Annotated, Any, ClassVar, Literal

import numpy as np

#: The BarrettHand's 8 joints in the order every joint array on the wire uses.
JOINT_NAMES = ("f1_spread", "f1_prox", "f1_dist", "f2_spread", "f2_prox", "f2_dist",
               "f3_prox", "f3_dist")
#: Its 4 degrees of freedom (``dofs_deg``): the spread and one per finger.
DOF_NAMES = ("spread", "f1", "f2", "f3")
#: Largest |entry| of a pose or |coordinate| (metres) the service accepts.
MAX_COORDINATE_M = 1000.0
#: Tolerance of the rigidity check on camera poses (orthonormal rotation).
RIGID_TOL = 1e-3


# ----------------------------------------------------------------------- checked numeric arrays


def finite_array(value: Any, shape: tuple[int, ...], name: str) -> np.ndarray:
    """``value`` (nested lists of numbers, or an array) as a float64 array of ``shape`` with
    finite entries; ``ValueError`` naming ``name`` otherwise. Booleans and strings are refused
    (true is not 1 m)."""
    if not isinstance(value, np.ndarray) and _has_non_number(value):
        raise ValueError(f"{name} must hold numbers only, got {value!r:.80}")
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be numbers of shape {shape}, got {value!r:.80}") from None
    if a.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite (no NaN or infinity)")
    return a


def _has_non_number(value: Any) -> bool:
    if isinstance(value, list | tuple):
        return any(_has_non_number(v) for v in value)
    return isinstance(value, bool) or not isinstance(value, int | float | np.number)


class Array:
    """Annotation of a numpy field that travels as nested JSON lists of ``shape``, checked by
    ``check`` (default: finite numbers of that shape). On the server, pydantic reads the hooks:
    validation through ``check``, serialization as lists, the JSON schema from the shape."""

    def __init__(self, shape: tuple[int, ...], description: str, check=None) -> None:
        self.shape, self.description = shape, description
        self.check = check or (lambda value: finite_array(value, shape, "the array"))

    def __get_pydantic_core_schema__(self, source: Any, handler: Any) -> Any:
        from pydantic_core import core_schema as cs

        listed = cs.float_schema(allow_inf_nan=False)
        for n in reversed(self.shape):
            listed = cs.list_schema(listed, min_length=n, max_length=n)
        return cs.no_info_plain_validator_function(
            self.check, json_schema_input_schema=listed,
            serialization=cs.plain_serializer_function_ser_schema(_as_lists, return_schema=listed))

    def __get_pydantic_json_schema__(self, schema: Any, handler: Any) -> dict:
        return {**handler(schema), "description": self.description}


class Doc:
    """Annotation giving a plain field its description in the JSON schema."""

    def __init__(self, description: str) -> None:
        self.description = description

    def __get_pydantic_json_schema__(self, schema: Any, handler: Any) -> dict:
        return {**handler(schema), "description": self.description}


def _as_lists(value: Any) -> Any:
    return np.asarray(value, dtype=np.float64).tolist()


def transform(value: Any, name: str) -> np.ndarray:
    """A 4×4 homogeneous transform: finite entries within ±:data:`MAX_COORDINATE_M`, last row
    [0, 0, 0, 1]."""
    m = finite_array(value, (4, 4), name)
    if np.abs(m).max() > MAX_COORDINATE_M:
        raise ValueError(f"{name} entries must lie within ±{MAX_COORDINATE_M:g}")
    if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{name} must have the last row [0, 0, 0, 1], got {m[3].tolist()}")
    return m


def rigid_pose(value: Any, name: str = "camera_pose", what: str = "camera→world") -> np.ndarray:
    """A rigid :func:`transform`: an orthonormal rotation with determinant +1 (within
    :data:`RIGID_TOL`)."""
    m = transform(value, name)
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=RIGID_TOL) or np.linalg.det(r) < 0:
        raise ValueError(f"{name} must be a rigid {what} transform (an orthonormal rotation "
                         "with determinant +1, metres)")
    return m


#: A 4×4 transform (row-major), as a float64 array.
Pose = Annotated[np.ndarray, Array((4, 4), "4×4, row-major")]
#: A camera→world pose, checked by :func:`rigid_pose`.
RigidPose = Annotated[np.ndarray, Array(
    (4, 4), "camera→world, rigid (an orthonormal rotation with determinant +1, last row "
    "[0, 0, 0, 1], metres)", check=rigid_pose)]


# ------------------------------------------------------------------------------- support plane


@dataclass(frozen=True, eq=False)
class SupportPlane:
    """The surface the object rests on: points x with n·x + d = 0, n (unit) pointing up. Made
    from any non-zero normal (it is normalised, the offset with it); ``ValueError`` otherwise."""

    normal: np.ndarray
    offset: float

    #: The rule of a plane given with views, said the same way wherever it is broken (the
    #: completion stream, the service): the views need their camera poses.
    NEEDS_POSES: ClassVar[str] = ("a support plane is in the world frame: it needs the views' "
                                  "camera poses (camera_pose)")
    #: The text form "nx,ny,nz,d": four decimal numbers, finite as floats (at most 9 digits
    #: before the point, exponents of at most two digits, so 1e999 does not match); the
    #: lookahead asks for a non-zero digit in the normal.
    PATTERN: ClassVar[re.Pattern] = re.compile(
        r"^(?=[^,]*[1-9]|[^,]*,[^,]*[1-9]|[^,]*,[^,]*,[^,]*[1-9])"
        + ",".join([r"[-+]?\d{1,9}(\.\d{1,20})?([eE][-+]?\d{1,2})?"] * 4) + "$")

    def __post_init__(self) -> None:
        n = np.asarray(self.normal, dtype=np.float64).reshape(-1)
        if n.shape != (3,) or not np.isfinite(n).all():
            raise ValueError(f"a support plane's normal must be 3 finite numbers, got {n}")
        if isinstance(self.offset, bool) or not math.isfinite(self.offset):
            raise ValueError(f"a support plane's offset d must be finite, got {self.offset}")
        norm = float(np.linalg.norm(n))
        if not 1e-9 <= norm < np.inf:
            raise ValueError("a support plane is [nx, ny, nz, d] with a non-zero normal n "
                             f"(pointing up), got the normal {n.tolist()}")
        object.__setattr__(self, "normal", n / norm)
        object.__setattr__(self, "offset", float(self.offset) / norm)

    @classmethod
    def from_values(cls, values: Any) -> SupportPlane:
        """From four numbers [nx, ny, nz, d] (the JSON form)."""
        p = finite_array(values, (4,), "support_plane")
        return cls(p[:3], float(p[3]))

    @classmethod
    def parse(cls, text: str) -> SupportPlane:
        """From "nx,ny,nz,d" (the query and command-line form, :attr:`PATTERN`)."""
        if not cls.PATTERN.match(text):
            raise ValueError(
                "support_plane is four numbers nx,ny,nz,d without spaces (like 0,0,1,-0.25 or "
                "1e-3; at most 9 digits before the point, exponents of at most two digits), the "
                f"normal not zero; got {text[:80]!r}")
        return cls.from_values([float(v) for v in text.split(",")])

    def as_array(self) -> np.ndarray:
        """[nx, ny, nz, d] with |n| = 1."""
        return np.array([*self.normal, self.offset])

    def height(self, points: np.ndarray) -> np.ndarray:
        """Signed distance of (n, 3) points above the plane (metres)."""
        return np.asarray(points, dtype=np.float64) @ self.normal + self.offset

    def transformed(self, pose: np.ndarray) -> SupportPlane:
        """The same plane in the frame whose pose (frame→here) is ``pose``."""
        pose = np.asarray(pose, dtype=np.float64)
        normal = pose[:3, :3].T @ self.normal
        return SupportPlane(normal, self.offset + float(self.normal @ pose[:3, 3]))

    def lowest(self, kind: str, size: Sequence[float], pose: np.ndarray) -> np.ndarray:
        """Height (m) above the plane of the lowest point of a box (full extents ``size``) or a
        cylinder ((radius, length) along its z) at (..., 4, 4) ``pose``: (...), negative below."""
        pose = np.asarray(pose, dtype=np.float64)
        down = np.einsum("...ji,j->...i", pose[..., :3, :3], self.normal)  # primitive's frame
        centre = self.height(pose[..., :3, 3])
        if kind == "box":
            return centre - 0.5 * np.abs(down) @ np.asarray(size, dtype=np.float64)
        radius, length = size
        cos = np.abs(down[..., 2])
        return centre - 0.5 * length * cos - radius * np.sqrt(np.clip(1.0 - cos * cos, 0.0, 1.0))

    @classmethod
    def __get_pydantic_core_schema__(cls, source: Any, handler: Any) -> Any:
        from pydantic_core import core_schema as cs

        listed = cs.list_schema(cs.float_schema(allow_inf_nan=False), min_length=4, max_length=4)
        return cs.no_info_plain_validator_function(
            lambda v: v if isinstance(v, SupportPlane) else cls.from_values(v),
            json_schema_input_schema=listed,
            serialization=cs.plain_serializer_function_ser_schema(
                lambda p: p.as_array().tolist(), return_schema=listed))


# ------------------------------------------------------------------------------------ a grasp


@dataclass(frozen=True, eq=False)
class Contact:
    """Where a link of the hand touches the object."""

    link: str
    point: Annotated[np.ndarray, Array((3,), "camera frame, metres")]
    normal: Annotated[np.ndarray, Array((3,), "unit, camera frame")]

    @classmethod
    def from_json(cls, c: Mapping[str, Any]) -> Contact:
        return cls(str(c["link"]), finite_array(c["point"], (3,), "contact point"),
                   finite_array(c["normal"], (3,), "contact normal"))


@dataclass(frozen=True, eq=False)
class Primitive:
    """One collision primitive of the hand at the grasp, placed by its kinematics."""

    link: Annotated[str, Doc("palm, f1_knuckle, f1_prox, f1_dist, …")]
    kind: Literal["box", "cylinder"]
    size: Annotated[list[float], Doc("box: full extents; cylinder: radius, length (z)")]
    pose: Annotated[np.ndarray, Array((4, 4), "4×4 primitive→camera (latest view)")]

    @classmethod
    def from_json(cls, p: Mapping[str, Any]) -> Primitive:
        return cls(str(p["link"]), p["kind"], [float(v) for v in p["size"]],
                   finite_array(p["pose"], (4, 4), "primitive pose"))


@dataclass(frozen=True, eq=False)
class Verification:
    """What lift-testing a grasp on the completion saw before it was returned (``verify=N``)."""

    tried: Annotated[bool, Doc(
        "whether it was lift-tested (the grasps ranked below the first that held, or beyond the "
        "N tried, were not)")]
    trials: Annotated[int, Doc("lift trials run (perturbed mass, friction, shake)")] = 0
    held: Annotated[int, Doc("trials in which the object stayed in the hand")] = 0
    first_drop: Annotated[str | None, Doc(
        "why the first trial that dropped it did; null when every trial held")] = None

    @property
    def held_all(self) -> bool:
        """Tried, and held in every trial."""
        return self.tried and self.held == self.trials

    @classmethod
    def from_json(cls, v: Mapping[str, Any]) -> Verification:
        drop = v.get("first_drop")
        return cls(bool(v["tried"]), int(v["trials"]), int(v["held"]),
                   None if drop is None else str(drop))


@dataclass(frozen=True, eq=False)
class WristRise:
    """How the palm of a table pinch rises while its fingers close: a table of the rise
    (metres, along the support plane's normal, i.e. the palm's −z) against the closing fingers'
    DOF (degrees; a robot reads it from the hand), linear between entries, from the hand's
    geometry; and the rise where the planned closing ends (``end_palm_pose``)."""

    dof_deg: Annotated[list[float], Doc("finger DOF (motor angle in J2 units), increasing")]
    rise_m: Annotated[list[float], Doc("palm rise at each DOF, metres, never decreasing")]
    end_m: Annotated[float, Doc("the rise where the planned closing ends, metres")]

    def at(self, dof_deg: float) -> float:
        """The rise (metres) at ``dof_deg`` (linear between entries, constant past the last)."""
        return float(np.interp(dof_deg, self.dof_deg, self.rise_m))

    @classmethod
    def from_json(cls, w: Mapping[str, Any]) -> WristRise:
        dofs, rises = [float(v) for v in w["dof_deg"]], [float(v) for v in w["rise_m"]]
        if not dofs or len(dofs) != len(rises):
            raise ValueError("wrist_rise needs as many rises as DOFs, at least one")
        return cls(dofs, rises, float(w["end_m"]))


@dataclass(frozen=True, eq=False)
class Grasp:
    """One planned grasp. Poses are 4×4 float64 arrays; ``joints_deg`` the 8 joints by name in
    degrees (``joint_array``: the same in :data:`JOINT_NAMES` order)."""

    palm_pose: Annotated[np.ndarray, Array((4, 4), "4×4 palm→camera (latest view)")]
    palm_pose_world: Annotated[np.ndarray, Array(
        (4, 4), "4×4 palm→world, when the latest view came with a camera_pose")] | None
    pregrasp_pose: Annotated[np.ndarray, Array(
        (4, 4), "4×4 palm→camera the robot moves to first: the palm backed off 0.2 m along its "
        "approach axis (−z), hand open at the grasp's spread; then approach and close")]
    pregrasp_pose_world: Annotated[np.ndarray, Array(
        (4, 4), "the pre-grasp pose palm→world, when the latest view came with a camera_pose")
    ] | None
    joints_deg: Annotated[dict[str, float], Doc(
        "the 8 joints by name (f1_spread, f1_prox, f1_dist, f2_spread, f2_prox, f2_dist, "
        "f3_prox, f3_dist), degrees")]
    dofs_deg: Annotated[np.ndarray, Array((4,), "spread, f1, f2, f3 DOFs, degrees")]
    epsilon: Annotated[float, Doc("Ferrari–Canny epsilon of the L1 grasp wrench space")]
    volume: float
    force_epsilon: Annotated[float, Doc(
        "epsilon of pure forces through the centre of mass (weight, inertia): the ranking's "
        "measure after force closure and palm contact")]
    palm_contact: Annotated[bool, Doc("the palm touches the object (a power grasp)")]
    approach_stop: Annotated[Literal["contact", "limit", "none"], Doc(
        "how to execute it: move from the pre-grasp pose toward palm_pose, stopping at the "
        "first touch (object or table); 'contact': the plan's approach ended touching the "
        "object, so go on past palm_pose (up to 5 cm) until it touches; 'limit': a fingertip "
        "grasp, stop at palm_pose untouched; then close ('none': planned without an approach)")]
    hold_probability: Annotated[float | None, Doc(
        "with a support plane, the ranking's estimate that the grasp holds when the object is "
        "lifted (a model learned from lift tests); null without one")]
    contacts: list[Contact]
    verification: Annotated[Verification | None, Doc(
        "with verify > 0, what the lift trials on the completion saw; null without")] = None
    hand: Annotated[list[Primitive], Doc(
        "the hand at this grasp (where its fingers closed) as collision primitives placed by "
        "its kinematics")] = field(default_factory=list)
    kind: Annotated[Literal["autograsp", "table pinch"], Doc(
        "'autograsp': the palm stays at palm_pose while the fingers close; 'table pinch': the "
        "palm faces the table and rises (wrist_rise) while the fingers close, their tips on the "
        "table (docs/service.md, 'Executing a table pinch')")] = "autograsp"
    wrist_rise: Annotated[WristRise | None, Doc(
        "a table pinch's palm rise against the fingers' DOF; null for an autograsp")] = None
    end_palm_pose: Annotated[np.ndarray, Array(
        (4, 4), "4×4 palm→camera where closing ends: palm_pose, risen for a table pinch")
    ] | None = None
    end_palm_pose_world: Annotated[np.ndarray, Array(
        (4, 4), "the same palm→world, when the latest view came with a camera_pose")] | None = None
    preshape_deg: Annotated[float, Doc(
        "the fingers' DOF (degrees) while the hand approaches, from which they close: 0 (open) "
        "but among obstacles, where an open hand would touch one")] = 0.0

    @property
    def joints(self) -> dict[str, float]:
        """``joints_deg`` (the name the client has always used)."""
        return self.joints_deg

    @property
    def joint_array(self) -> np.ndarray:
        return np.array([self.joints_deg[name] for name in JOINT_NAMES], dtype=np.float64)

    @classmethod
    def from_json(cls, g: Mapping[str, Any]) -> Grasp:
        """From the JSON of ``GET /grasp`` (every array checked)."""
        def pose(key: str) -> np.ndarray | None:
            return None if g.get(key) is None else finite_array(g[key], (4, 4), key)

        probability = g.get("hold_probability")
        return cls(
            palm_pose=pose("palm_pose"), palm_pose_world=pose("palm_pose_world"),
            pregrasp_pose=pose("pregrasp_pose"), pregrasp_pose_world=pose("pregrasp_pose_world"),
            joints_deg={name: float(g["joints_deg"][name]) for name in JOINT_NAMES},
            dofs_deg=finite_array(g["dofs_deg"], (4,), "dofs_deg"),
            epsilon=float(g["epsilon"]), volume=float(g["volume"]),
            force_epsilon=float(g["force_epsilon"]), palm_contact=bool(g["palm_contact"]),
            approach_stop=g.get("approach_stop", "contact"),
            hold_probability=None if probability is None else float(probability),
            contacts=[Contact.from_json(c) for c in g["contacts"]],
            verification=None if g.get("verification") is None
            else Verification.from_json(g["verification"]),
            hand=[Primitive.from_json(p) for p in g.get("hand", ())],
            kind=g.get("kind", "autograsp"),
            wrist_rise=None if g.get("wrist_rise") is None
            else WristRise.from_json(g["wrist_rise"]),
            end_palm_pose=pose("end_palm_pose"), end_palm_pose_world=pose("end_palm_pose_world"),
            preshape_deg=float(g.get("preshape_deg", 0.0)),
        )


# ------------------------------------------------------------------------------------ the mask

#: The values a mask may hold without a label (0 = background).
MASK_VALUES = ({0, 1}, {0, 255})


def object_pixels(mask: Any, label: int | None = None, *, kind: str | None = None) -> np.ndarray:
    """(H, W) bool: the object's pixels of a boolean, 0/1 or 0/255 mask (every object pixel the
    same 1 or 255), or the pixels equal to ``label`` in a label image. Anything else raises
    ``ValueError`` naming what the mask is (``kind``, default its dtype) and the values it
    holds."""
    m = np.asarray(mask)
    if label is not None:
        inside = m == label
        if not inside.any() and m.size:
            values = np.unique(m)
            shown = ", ".join(f"{v:g}" for v in values[:8].tolist()) + (
                ", …" if len(values) > 8 else "")
            raise ValueError(f"object_label {label} is not in the label image ({kind or m.dtype}"
                             f"), which holds {shown}: the object's pixels must have that value")
        return inside
    if m.dtype == bool:
        return m
    inside = m != 0
    if m.dtype.kind in "iuf" and inside.any():
        low, high = m[inside].min(), m[inside].max()
        if low == high and float(high) in (1.0, 255.0):
            return inside
    elif m.dtype.kind in "iuf":
        return inside
    values = np.unique(m)
    shown = ", ".join(f"{v:g}" for v in values[:8].tolist()) + (", …" if len(values) > 8 else "")
    raise ValueError(f"the mask ({kind or m.dtype}) holds {len(values)} distinct values "
                     f"({shown}); a mask is boolean, 0/1 or 0/255 with 0 = background, or a label "
                     "image with object_label, the value of the object's pixels")


# ------------------------------------------------------------------------------- the encodings


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def png_bytes(image: np.ndarray) -> bytes:
    """A (H, W) uint8 or uint16 array as a single-channel greyscale PNG (8- or 16-bit), written
    with zlib (rows filtered "Up", PNG filter type 2), so that the client needs no imaging
    library."""
    a = np.asarray(image)
    if a.ndim != 2 or a.dtype not in (np.uint8, np.uint16) or min(a.shape) < 1:
        raise ValueError(f"expected an (H, W) uint8 or uint16 image, got {a.dtype} {a.shape}")
    h, w = a.shape
    rows = np.ascontiguousarray(a, dtype=">u2" if a.dtype == np.uint16 else "u1")
    raw = rows.view(np.uint8).reshape(h, -1)
    up = raw.copy()
    up[1:] -= raw[:-1]  # byte-wise, modulo 256, as the filter defines it
    scanlines = np.hstack([np.full((h, 1), 2, dtype=np.uint8), up])

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    header = struct.pack(">IIBBBBB", w, h, 8 * a.dtype.itemsize, 0, 0, 0, 0)  # greyscale
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header)
            + chunk(b"IDAT", zlib.compress(scanlines.tobytes(), 6)) + chunk(b"IEND", b""))


def depth_png16_mm(depth_m: np.ndarray) -> dict:
    """``depth`` field for metric depth (H, W): 16-bit PNG in millimetres, 0 = no return."""
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if d.min(initial=0.0) < 0:
        raise ValueError("depth must be ≥ 0 m")
    mm = np.round(d * 1000.0)
    if mm.max(initial=0.0) > 65535:
        raise ValueError("depth beyond 65.535 m does not fit a 16-bit PNG in millimetres")
    return depth_png16_raw(mm.astype(np.uint16))


def depth_png16_raw(millimetres: np.ndarray) -> dict:
    """``depth`` field for a uint16 millimetre image (the camera's own values, losslessly)."""
    h, w = np.shape(millimetres)
    return {"encoding": "png16_mm", "width": w, "height": h, "data": b64(png_bytes(millimetres))}


def depth_f32_m(depth_m: np.ndarray) -> dict:
    """``depth`` field for metric depth (H, W) as raw little-endian float32 metres."""
    d = np.asarray(depth_m, dtype="<f4")
    h, w = d.shape
    return {"encoding": "f32_m", "width": w, "height": h, "data": b64(d.tobytes())}


def mask_png(mask: np.ndarray) -> str:
    """``mask`` field: (H, W) bool-like, non-zero = object, as an 8-bit PNG (0 / 255)."""
    return b64(png_bytes(np.where(np.asarray(mask) != 0, 255, 0).astype(np.uint8)))


def intrinsics_field(intrinsics: Mapping[str, float]) -> dict:
    """``intrinsics`` field (fx, fy, cx, cy) from a mapping with those keys."""
    return {k: float(intrinsics[k]) for k in ("fx", "fy", "cx", "cy")}


def grid_field(grid: Any) -> dict:
    """``grid`` field from an object with ``pack()`` (8000 bytes: 40³ bits) and
    ``grid_to_camera`` (4×4), such as the service's ``completion.grid.VoxelGrid``."""
    return {"data": b64(grid.pack()), "grid_to_camera": _as_lists(grid.grid_to_camera)}
