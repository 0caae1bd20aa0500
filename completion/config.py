"""The configuration of a completion model: one frozen dataclass, stored in every checkpoint.

:data:`DEFAULT_CONFIGS` builds exactly the shipped architectures (``completion/weights/``), so
``python -m completion.train --model X`` with no ``--config`` trains the shipped kind of X.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal, get_args

ModelKind = Literal["single_view", "mvp", "mvt", "lstm"]
MODEL_KINDS: tuple[str, ...] = get_args(ModelKind)
Kernel = Literal["softmax", "relu"]
KERNELS: tuple[str, ...] = get_args(Kernel)


@dataclass(frozen=True)
class ModelConfig:
    """Everything needed to rebuild a model; stored as a plain dict inside every checkpoint.

    kind: which model. grid_size: G. channels: conv channels of the U-Net levels, each level a
    stride-2 conv and a same-size conv (G must be divisible by 2**len(channels)); the decoder
    mirrors them with skips. top_channels: channels of the last up-sampling to G³ (the raw input
    is concatenated to them before the output conv). token_channels: the bottleneck volume is
    reduced to this many channels before it is flattened into a view's token. embed_dim: D, the
    token size. n_heads: H (D % H == 0). n_layers: Transformer blocks (mvp/mvt) or LSTM layers.
    mlp_ratio: hidden width of the block's MLP in units of D. kernel: Performer kernel (mvp
    only; the paper's FAVOR+ softmax or ReLU). n_features: M for the FAVOR+ kernel.
    qk_norm: normalise each head's query and key per position (LayerNorm without parameters)
    before attention. It bounds ‖k‖, so FAVOR+ key features cannot underflow to zero and make
    the normaliser's gradient overflow (training otherwise diverged to NaN); per position, so
    nothing crosses time.
    value_rotation: rotary values in the attention towers (mvp, mvt), in degrees per view of
    the base rate, 0 = off. Channel pair i of each head's value turns by
    t · (i mod 7) · value_rotation at view t and the attention output turns back by the current
    view's angles, so a past view's features reach the current one rotated by the view offset
    alone (:func:`completion.towers.value_angles`). Without it a value is a linear map of its
    token plus the position code and cannot turn with the offset: the memory can carry only
    what does not change as the camera moves. 30 matches the simulated pans (30° a view).
    registered_input: a second input channel, the surface earlier views of the same still object
    saw, carried into this view's grid with the camera poses
    (:meth:`completion.evidence.RegisteredEvidence.seen`); the U-Net's both encoders and the
    decoder's raw-input skip take it beside the view's own surface. Without poses it is empty.
    seed: weight initialisation and the initial FAVOR+ draw.
    """

    kind: ModelKind = "mvp"
    grid_size: int = 40
    channels: tuple[int, ...] = (16, 32, 64)
    top_channels: int = 8
    token_channels: int = 16
    embed_dim: int = 256
    n_heads: int = 4
    n_layers: int = 1
    mlp_ratio: int = 2
    kernel: Kernel = "softmax"
    n_features: int = 128
    qk_norm: bool = False
    value_rotation: float = 0.0
    registered_input: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        object.__setattr__(self, "value_rotation", float(self.value_rotation))
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"kind must be one of {MODEL_KINDS}, got {self.kind!r}")
        if self.kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {self.kernel!r}")
        if not self.channels or any(c < 1 for c in self.channels):
            raise ValueError(
                f"channels must be a non-empty tuple of positive ints, got {self.channels}"
            )
        step = 2 ** len(self.channels)
        if self.grid_size < step or self.grid_size % step:
            raise ValueError(
                f"grid_size {self.grid_size} must be a positive multiple of "
                f"2**len(channels) = {step}"
            )
        for name in ("embed_dim", "n_heads", "n_layers", "mlp_ratio", "n_features",
                     "top_channels", "token_channels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.embed_dim % self.n_heads:
            raise ValueError(
                f"embed_dim {self.embed_dim} must be divisible by n_heads {self.n_heads}"
            )
        if self.embed_dim % 2:
            raise ValueError(f"sinusoidal encoding needs an even embed_dim, got {self.embed_dim}")
        if not (math.isfinite(self.value_rotation) and 0 <= self.value_rotation <= 180):
            raise ValueError(f"value_rotation must be in [0, 180] degrees per view, "
                             f"got {self.value_rotation}")
        if self.value_rotation and (self.kind not in ("mvp", "mvt") or
                                    (self.embed_dim // self.n_heads) % 2):
            raise ValueError("value_rotation needs an attention model (mvp, mvt) with an even "
                             f"head size, got kind {self.kind!r}, head size "
                             f"{self.embed_dim // self.n_heads}")

    def to_dict(self) -> dict[str, Any]:
        """Plain types only (lists, not tuples), loadable by ``torch.load(weights_only=True)``."""
        out = {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}
        out["channels"] = list(self.channels)
        return out

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ModelConfig:
        """Inverse of :meth:`to_dict`; unknown keys raise ValueError."""
        unknown = set(data) - {f.name for f in dataclasses.fields(cls)}
        if unknown:
            raise ValueError(f"unknown ModelConfig fields: {sorted(unknown)}")
        return cls(**data)

    def replace(self, **changes: Any) -> ModelConfig:
        return dataclasses.replace(self, **changes)


_ATTENTION = {"qk_norm": True, "value_rotation": 30.0}
"""What the shipped attention models (MVP, MVP3, MVP6, MVT) add to the dataclass's defaults."""

DEFAULT_CONFIGS: dict[str, ModelConfig] = {
    "single_view": ModelConfig(kind="single_view"),
    "mvp": ModelConfig(kind="mvp", **_ATTENTION),
    "mvp3": ModelConfig(kind="mvp", **_ATTENTION),
    "mvp6": ModelConfig(kind="mvp", **_ATTENTION),
    "mvt": ModelConfig(kind="mvt", **_ATTENTION),
    "lstm": ModelConfig(kind="lstm"),
    "mvp_relu": ModelConfig(kind="mvp", kernel="relu", **_ATTENTION),
    "mvp_posed": ModelConfig(kind="mvp", registered_input=True, **_ATTENTION),
}
"""The architecture of each shipped model by name (MVP3/MVP6 differ from MVP only in the views
they trained on); ``mvp_relu`` is MVP with the paper's ReLU kernel (no shipped weights);
``mvp_posed`` is MVP with the registered surface of earlier posed views as a second input channel
(the model a session with camera poses runs, :mod:`completion.evidence`)."""


#: The shipped weights a registered MVP stream runs when its views come with camera poses
#: (:class:`completion.stream.CompletionStream`'s ``posed_model``).
POSED_MODEL = "mvp_posed"


def default_config(name: str, **overrides: Any) -> ModelConfig:
    """The default :class:`ModelConfig` for a model name (see :data:`DEFAULT_CONFIGS`)."""
    if name not in DEFAULT_CONFIGS:
        raise ValueError(f"unknown model name {name!r}; expected one of {sorted(DEFAULT_CONFIGS)}")
    return DEFAULT_CONFIGS[name].replace(**overrides)
