"""The rows of the evaluation: each one object that turns a sequence's views into occupancy
probabilities, with the threshold that decides occupied.

- :class:`ModelRow`: a trained model, run over the whole sequence (its parallel form, which is
  causal and equals streaming); the benchmark streams the same model through
  :class:`completion.stream.CompletionStream`, as the service does.
- :class:`MemoryOffRow`: the shipped MVP given each view alone (a fresh memory every view).
- :class:`RegisteredRow`: the shipped MVP streamed with the views' camera poses
  (:class:`completion.stream.CompletionStream`, as the service does: :mod:`completion.evidence`).
- :class:`PriorRow`: one fixed shape per condition, whatever the input (:mod:`completion.prior`).
- :class:`FusionRow`: no learning, the views registered with the known camera poses
  (:func:`fuse`); the benchmark's fusion row fuses with the same function.

:func:`load_models` reads a run's checkpoints (once per worker), :func:`make_rows` makes its
rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from completion import grid as G
from completion.config import POSED_MODEL
from completion.scenes import Sequence
from grasp.evaluate.config import (
    DEFAULT_THRESHOLD,
    FUSION,
    MEMORY_OFF,
    PRIOR,
    REGISTERED,
    Settings,
    checkpoints_loaded,
)


class Row(Protocol):
    name: str

    def probabilities(self, seq: Sequence) -> np.ndarray:
        """(L, 40, 40, 40): view t's occupancy probabilities in view t's grid."""
        ...

    def threshold(self, condition: str) -> float:
        """Probabilities at or above it are occupied."""
        ...


def _inputs(seq: Sequence):
    import torch

    return torch.from_numpy(seq.inputs[None].astype(np.float32))


@dataclass
class ModelRow:
    name: str
    model: Any  # a completion.model network, in eval mode
    decision: float  # the validation-chosen threshold the checkpoint carries

    def probabilities(self, seq: Sequence) -> np.ndarray:
        import torch

        with torch.no_grad():
            return torch.sigmoid(self.model(_inputs(seq)))[0].numpy()

    def threshold(self, condition: str) -> float:
        return self.decision


@dataclass
class MemoryOffRow(ModelRow):
    """The L views as L sequences of one view each."""

    def probabilities(self, seq: Sequence) -> np.ndarray:
        import torch

        with torch.no_grad():
            return torch.sigmoid(self.model(_inputs(seq)[0][:, None]))[:, 0].numpy()


@dataclass
class RegisteredRow(ModelRow):
    """The views streamed with their camera poses as the service streams them: the posed model
    (``mvp_posed``) fed what earlier views saw, each view's answer fused with the earlier ones."""

    posed: Any = None  # the registered_input model (completion.config.POSED_MODEL)

    def probabilities(self, seq: Sequence) -> np.ndarray:
        from completion.stream import CompletionStream

        stream = CompletionStream(self.model, registered=True, posed_model=self.posed)
        logits = []
        for inputs, grid, pose in zip(seq.inputs, seq.grid_to_camera, seq.camera_to_world,
                                      strict=True):
            stream.add_view(grid=G.VoxelGrid(inputs, grid), camera_to_world=pose)
            logits.append(stream.logits)
        return 1.0 / (1.0 + np.exp(-np.stack(logits)))


@dataclass
class PriorRow:
    name: str
    prior: Any  # completion.prior.Prior

    def probabilities(self, seq: Sequence) -> np.ndarray:
        return self.prior.probabilities(seq.meta["condition"], len(seq))

    def threshold(self, condition: str) -> float:
        return self.prior.thresholds[condition]


@dataclass
class FusionRow:
    name: str = FUSION

    def probabilities(self, seq: Sequence) -> np.ndarray:
        return registered_fusion(seq.inputs, seq.grid_to_camera, seq.camera_to_world)

    def threshold(self, condition: str) -> float:
        return 0.5  # a bool grid: meshed between empty and occupied


def load_models(settings: Settings) -> dict[str, ModelRow]:
    """The checkpoints these rows run (MVP for the memory-off row too), each as its row."""
    from completion.model import load_model, read_checkpoint

    models: dict[str, ModelRow] = {}
    for name, path in settings.model_paths:
        if name not in checkpoints_loaded(settings.rows):
            continue
        model = load_model(path).eval()
        # the validation-chosen decision threshold: an attribute of the loaded model, or the
        # checkpoint's "threshold" entry, else 0.5
        threshold = getattr(model, "threshold", None)
        if threshold is None:
            threshold = read_checkpoint(path).get("threshold", DEFAULT_THRESHOLD)
        models[name] = ModelRow(name, model, float(threshold))
    return models


def make_rows(settings: Settings, models: dict[str, ModelRow]) -> dict[str, Row]:
    """name -> row, for ``settings.rows`` in that order (``models`` from :func:`load_models`)."""
    from completion.prior import load_prior

    rows: dict[str, Row] = {}
    for name in settings.rows:
        if name == FUSION:
            rows[name] = FusionRow()
        elif name == PRIOR:
            rows[name] = PriorRow(name, load_prior(settings.prior_path))
        elif name == MEMORY_OFF:
            rows[name] = MemoryOffRow(name, models["mvp"].model, models["mvp"].decision)
        elif name == REGISTERED:
            rows[name] = RegisteredRow(name, models["mvp"].model, models["mvp"].decision,
                                       models[POSED_MODEL].model)
        else:
            rows[name] = models[name]
    return rows


# ------------------------------------------------------------------------------ fusion

#: Sub-voxel offsets (in voxels) at which an observed voxel is carried into another grid, so that
#: a coarser source grid leaves no holes in a finer destination grid.
_SUBVOXEL = np.array(
    [[x, y, z] for x in (-0.25, 0.25) for y in (-0.25, 0.25) for z in (-0.25, 0.25)]
)


def fuse(world_points: list[np.ndarray], grid_to_camera: np.ndarray,
         camera_to_world: np.ndarray) -> np.ndarray:
    """The registration reference: every view's points (world frame) in one 40³ grid of the
    camera at ``camera_to_world``, occupied where any point falls."""
    seen = np.concatenate(world_points)
    to_camera = np.linalg.inv(camera_to_world)
    return G.voxelize_points(G.transform_points(seen, to_camera), grid_to_camera)


def registered_fusion(
    inputs: np.ndarray, grid_to_camera: np.ndarray, camera_to_world: np.ndarray
) -> np.ndarray:
    """(L, 40, 40, 40) bool, view t = views 0…t's observed voxels fused (:func:`fuse`) in grid t.

    inputs : (L, 40, 40, 40) bool observed voxels; grid_to_camera, camera_to_world : (L, 4, 4)
    Each observed voxel (8 sub-voxel points) goes grid s → camera s → world → camera t → grid t.
    """
    inputs = np.asarray(inputs, dtype=bool)
    n = len(inputs)
    if inputs.shape[1:] != G.GRID_SHAPE or grid_to_camera.shape != (n, 4, 4):
        raise ValueError("inputs must be (L, 40, 40, 40) with (L, 4, 4) transforms")
    fused = np.zeros_like(inputs)
    world: list[np.ndarray] = []
    for t in range(n):
        idx = np.argwhere(inputs[t]).astype(np.float64)
        sub = (idx[:, None, :] + _SUBVOXEL[None]).reshape(-1, 3)
        cam = G.indices_to_points(sub, grid_to_camera[t])
        world.append(G.transform_points(cam, camera_to_world[t]))
        fused[t] = fuse(world, grid_to_camera[t], camera_to_world[t])
    return fused
