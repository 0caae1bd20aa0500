"""Encoding views the way ``POST /views`` expects them: depth images, masks, grids, intrinsics.

Used by :class:`service.grasp_client.GraspClient` (what a robot program should use), by
:mod:`service.load` and the tests, which build request bodies by hand::

    seq = make_sequence("camera_pan", "test", 0, keep_depth=True)
    for body in scene_views(seq):
        body["session_id"] = session_id  # after the first answer
        httpx.post(f"{url}/views", json=body)
"""

from __future__ import annotations

import base64
import io

import numpy as np

from completion.grid import VoxelGrid


def png_bytes(image: np.ndarray) -> bytes:
    """A (H, W) uint8 or uint16 array as single-channel PNG bytes (8- or 16-bit)."""
    from PIL import Image

    a = np.asarray(image)
    if a.ndim != 2 or a.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"expected an (H, W) uint8 or uint16 image, got {a.dtype} {a.shape}")
    buffer = io.BytesIO()
    Image.fromarray(a).save(buffer, format="PNG")
    return buffer.getvalue()


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


def depth_png16_mm(depth_m: np.ndarray) -> dict:
    """``depth`` field for metric depth (H, W): 16-bit PNG in millimetres, 0 = no return."""
    d = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
    if d.min(initial=0.0) < 0:
        raise ValueError("depth must be ≥ 0 m")
    mm = np.round(d * 1000.0)
    if mm.max(initial=0.0) > 65535:
        raise ValueError("depth beyond 65.535 m does not fit a 16-bit PNG in millimetres")
    h, w = d.shape
    return {
        "encoding": "png16_mm",
        "width": w,
        "height": h,
        "data": b64(png_bytes(mm.astype(np.uint16))),
    }


def depth_f32_m(depth_m: np.ndarray) -> dict:
    """``depth`` field for metric depth (H, W) as raw little-endian float32 metres."""
    d = np.asarray(depth_m, dtype="<f4")
    h, w = d.shape
    return {"encoding": "f32_m", "width": w, "height": h, "data": b64(d.tobytes())}


def mask_png(mask: np.ndarray) -> str:
    """``mask`` field: (H, W) bool-like, non-zero = object, as an 8-bit PNG (0 / 255)."""
    return b64(png_bytes(np.where(np.asarray(mask) != 0, 255, 0).astype(np.uint8)))


def grid_field(grid: VoxelGrid) -> dict:
    """``grid`` field: packed 40³ occupancy bits and ``grid_to_camera``."""
    return {"data": b64(grid.pack()), "grid_to_camera": np.asarray(grid.grid_to_camera).tolist()}


def intrinsics_field(intrinsics: dict) -> dict:
    """``intrinsics`` field (fx, fy, cx, cy) from an Intrinsics.as_dict()-like mapping."""
    return {k: float(intrinsics[k]) for k in ("fx", "fy", "cx", "cy")}


def scene_views(sequence, *, with_pose: bool = True) -> list[dict]:
    """``POST /views`` bodies (without session_id) for a simulated sequence kept with depth.

    ``sequence``: a :class:`completion.scenes.Sequence` made with ``keep_depth=True``; each view is
    a 16-bit millimetre depth PNG with its object mask and intrinsics, and (with_pose) its camera
    pose.
    """
    if sequence.depth is None or sequence.mask is None:
        raise ValueError("the sequence has no depth images: make it with keep_depth=True")
    intrinsics = intrinsics_field(sequence.meta["intrinsics"])
    bodies = []
    for t in range(len(sequence.depth)):
        body = {
            "depth": depth_png16_mm(sequence.depth[t]),
            "intrinsics": intrinsics,
            "mask": mask_png(sequence.mask[t] >= 0),
        }
        if with_pose:
            body["camera_pose"] = sequence.camera_to_world[t].tolist()
        bodies.append(body)
    return bodies
