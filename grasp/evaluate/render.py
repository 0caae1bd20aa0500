"""Pictures of a grasp: the BarrettHand on the mesh from two viewpoints (pybullet TinyRenderer).

    python -m grasp.evaluate.render MESH --out grasp.png [--candidates 64] [--seed 0]

plans a grasp on the mesh file (any format trimesh reads; units are metres) and saves a PNG with
two views: from the side, across the fingers' closing plane, and from above the object looking
back at the palm. Library use: :func:`render_grasp` returns the images, :func:`save_grasp_figure`
writes the PNG for a given :class:`grasp.hand.autograsp.GraspResult`.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import trimesh

from completion.bullet import pybullet
from completion.cli import HelpWithDefaults
from grasp.evaluate.picture import GraspWorld
from grasp.hand.collision import check_mesh
from grasp.hand.result import GraspResult

#: Field of view (degrees) of the picture cameras.
FOV_DEG = 40.0


def _views(
    points: np.ndarray, palm_pose: np.ndarray, above: np.ndarray | None = None
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(eye, target, up) of two cameras framing (n, 3) ``points`` (mesh corners, hand links).

    One looks across the fingers' closing plane from the side, one at the palm past the object.
    ``above`` (a unit vector, a table's normal): a camera that would look from below is mirrored
    to the same height above, so that no table hides the grasp.
    """
    x, y, z = palm_pose[:3, 0], palm_pose[:3, 1], palm_pose[:3, 2]
    lo, hi = points.min(axis=0), points.max(axis=0)
    target = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 0.05)
    distance = radius / np.sin(np.radians(FOV_DEG) / 2.0)
    side = x + 0.35 * y - 0.25 * z
    front = z + 0.6 * x + 0.5 * y
    views = []
    for direction, up in ((side, z), (front, y)):
        direction = direction / np.linalg.norm(direction)
        if above is not None and np.dot(direction, above) < 0.0:
            direction = direction - 2.0 * np.dot(direction, above) * above
        up = up - np.dot(up, direction) * direction
        views.append((target + distance * direction, target, up / np.linalg.norm(up)))
    return views


def render_grasp(
    mesh: trimesh.Trimesh,
    result: GraspResult,
    *,
    width: int = 480,
    height: int = 480,
    others: Sequence[tuple[trimesh.Trimesh, Sequence[float]]] = (),
    above: Sequence[float] | None = None,
) -> list[np.ndarray]:
    """Render ``result``'s hand on ``mesh`` (the object, :class:`GraspWorld`'s orange) from two
    viewpoints; ``others``: more meshes drawn beside it, each (mesh, RGBA), such as the table and
    the neighbours (pictured only: the hand's pose is the result's); ``above``: the table's
    normal, the side every camera looks from.

    Returns
    -------
    list of two (height, width, 3) uint8 RGB images.
    """
    check_mesh(mesh)
    if width < 16 or height < 16:
        raise ValueError(f"image size must be at least 16×16, got {width}×{height}")
    images = []
    with GraspWorld(mesh) as world:
        for other, rgba in others:
            shape = world.client.createVisualShape(
                pybullet.GEOM_MESH, vertices=np.asarray(other.vertices, float).tolist(),
                indices=np.asarray(other.faces, np.int32).ravel().tolist(),
                normals=np.asarray(other.vertex_normals).tolist(), rgbaColor=list(rgba))
            world.client.createMultiBody(baseMass=0.0, baseVisualShapeIndex=shape)
        world.set_hand(result.end_palm_pose, result.joints_deg)
        hand = np.array([pose[:3, 3] for pose in world.link_poses().values()])
        points = np.vstack([mesh.bounds, *(o.bounds for o, _ in others), hand,
                            hand + 0.06 * result.palm_pose[:3, 2]])
        normal = None if above is None else np.asarray(above, float) / np.linalg.norm(above)
        for eye, target, up in _views(points, np.asarray(result.palm_pose), normal):
            view = world.client.computeViewMatrix(eye.tolist(), target.tolist(), up.tolist())
            proj = world.client.computeProjectionMatrixFOV(FOV_DEG, width / height, 0.01, 5.0)
            _, _, rgba, _, _ = world.client.getCameraImage(
                width,
                height,
                view,
                proj,
                renderer=pybullet.ER_TINY_RENDERER,
                lightDirection=(eye - target + np.array([0.0, 0.0, 0.5])).tolist(),
                shadow=0,
            )
            images.append(np.asarray(rgba, dtype=np.uint8).reshape(height, width, 4)[..., :3])
    return images


def _caption(result: GraspResult) -> str:
    j = result.joints_deg
    return (
        f"{'OK' if result.success else 'FAIL'}: {result.reason}; ε = {result.epsilon:.3f}, "
        f"volume = {result.volume:.3f}\nspread {j.f1_spread:.1f}°, "
        f"f1 {j.f1_prox:.1f}/{j.f1_dist:.1f}°, f2 {j.f2_prox:.1f}/{j.f2_dist:.1f}°, "
        f"f3 {j.f3_prox:.1f}/{j.f3_dist:.1f}°"
    )


def save_grasp_figure(
    mesh: trimesh.Trimesh,
    result: GraspResult,
    path: str | Path,
    *,
    title: str = "",
    size: int = 480,
) -> Path:
    """Write a PNG with the two views of :func:`render_grasp` side by side; return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    images = render_grasp(mesh, result, width=size, height=size)
    fig, axes = plt.subplots(1, len(images), figsize=(4.0 * len(images), 4.5), dpi=size / 4.0)
    for ax, image, label in zip(axes, images, ("side", "toward the palm"), strict=True):
        ax.imshow(image)
        ax.set_title(label, fontsize=9)
        ax.axis("off")
    fig.suptitle((title + "\n" if title else "") + _caption(result), fontsize=8)
    fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.80, wspace=0.02)
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(formatter_class=HelpWithDefaults,
        prog="python -m grasp.evaluate.render",
        description="Plan a BarrettHand grasp on a mesh file and save a picture of it.",
    )
    parser.add_argument(
        "mesh", type=Path, help="mesh file (OBJ, STL, PLY, ...; metres) or an object id (named/mug)"
    )
    parser.add_argument("--out", type=Path, default=Path("grasp.png"), help="output PNG")
    parser.add_argument("--candidates", type=int, default=64, help="candidate grasps to try")
    parser.add_argument("--seed", type=int, default=0, help="seed of the candidates")
    parser.add_argument("--scale", type=float, default=1.0, help="multiply the mesh by this")
    args = parser.parse_args(argv)

    from grasp.cli import read_mesh_argument
    from grasp.planner import plan

    mesh = read_mesh_argument(parser, args.mesh, scale=args.scale)
    best = plan(mesh, n_candidates=args.candidates, seed=args.seed, top_k=1)[0]
    out = save_grasp_figure(mesh, best, args.out, title=args.mesh.name)
    print(f"{out}: {_caption(best)}")


if __name__ == "__main__":
    main()
