"""Shape-completion networks: Single-View, MVP (causal Performer memory), MVT and LSTM baselines.

Axis letters used in shape comments and docstrings:

    B  batch (sequences)                 L  views in a sequence (time)
    N  frames in one flat batch (B·L)    G  grid side (40); a grid is (G, G, G) indexed (i, j, k)
    C  conv channels                     D  embedding size
    H  attention heads                   E  head size (D / H)
    M  random features (FAVOR+) or E (ReLU kernel)
    T  views held in an MVT key/value cache (grows with the stream)
    P  tokens per view: 1, or g³ places of the bottleneck with ``context="place"``

Every model maps a causal sequence of input occupancy grids to per-view occupancy logits, each in
the grid of its own input view (so the latest output is in the latest camera frame), in two forms
that give the same numbers:

* parallel: ``model(seq)`` (B, L, G, G, G) -> logits (B, L, G, G, G);
* streaming: ``state = model.init_state(B)``, then ``logits, state = model.step(state, frame)``
  with frame (B, G, G, G) -> logits (B, G, G, G).

A state is a flat ``dict[str, Tensor]`` (see :func:`state_to_bytes`). The view counter ``"t"`` is
a 0-d int64 tensor; the MVP memory (S, z) has a size independent of the number of views.

The four kinds share one 3-D U-Net: :class:`Encoder` (the local tower: G³ -> feature volumes at
G/2, G/4, G/8) and :class:`Decoder` (bottleneck + the local tower's skips + the raw input -> G³
logits), so the surface the camera saw reaches the output directly. Except for ``single_view``
they have the paper's two towers: a context encoder (same shape, its own weights) turns each
frame's bottleneck volume into tokens (:class:`Bridge`: one per view, or with
``context="place"`` one per place of the g³ bottleneck with a learned position code of the place,
:class:`PlaceBridge`), a causal sequence model (Performer,
exact Transformer or LSTM; fp32 even under bf16 autocast) relates it to the past, and its output,
mapped back to a bottleneck volume, is added to the local bottleneck before decoding (the paper
adds the two towers' embeddings). No normalisation statistic crosses frames (GroupNorm per frame,
LayerNorm per token).
"""

from __future__ import annotations

import dataclasses
import io
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import torch
from torch import Tensor, nn

from completion.conv import Conv3d
from completion.performer import FeatureMap, Kernel
from completion.shift import ShiftMemory
from completion.towers import AttentionTower, LSTMTower

ModelKind = Literal["single_view", "mvp", "mvt", "lstm"]
MODEL_KINDS: tuple[str, ...] = get_args(ModelKind)
PositionalEncoding = Literal["sinusoidal", "none"]
Context = Literal["view", "place", "both"]
Norm = Literal["group", "none"]

State = dict[str, Tensor]
KV_CACHE_SUFFIXES = (".k", ".v")

CHECKPOINT_FORMAT = "mvp-grasp/completion-checkpoint"
CHECKPOINT_VERSION = 2

GRID_CONVENTION: dict[str, Any] = {
    "shape": [40, 40, 40],
    "axes": "grid index (i, j, k) along camera (x, y, z), OpenCV optical frame",
    "fit": "bbox centre of observed points at index (20, 20, 18), resolution = max extent / 32",
    "inputs": "observed surface points voxelized, occupied = 1",
    "targets": "complete object(s), solid",
}
"""Stored in every checkpoint (DESIGN.md §3); training may overwrite it via ``grid=...``."""

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


@dataclass(frozen=True)
class ModelConfig:
    """Everything needed to rebuild a model; stored as a plain dict inside every checkpoint.

    kind: which model. grid_size: G. channels: conv channels of the U-Net levels, each level a
    stride-2 conv and a same-size conv (G must be divisible by 2**len(channels)); the decoder
    mirrors them with skips. conv_kernel: 3 or 4 (the stride-2 convs). norm: GroupNorm per frame
    after each conv, or none. top_channels: channels of the last up-sampling to G³ (the raw input
    is concatenated to them before the output conv). token_channels: the bottleneck volume is
    reduced to this many channels before it is flattened into a view's token. embed_dim: D, the
    token size. n_heads: H (D % H == 0).
    n_layers: Transformer blocks (mvp/mvt) or LSTM layers. mlp_ratio: hidden width of the block's
    MLP in units of D. kernel: Performer kernel (mvp only). n_features: M for the FAVOR+ kernel.
    pos_encoding / pos_base: sinusoidal encoding of the view index t, frequencies pos_base^(-2i/D).
    qk_norm: normalise each head's query and key per position (LayerNorm without parameters)
    before attention. It bounds ‖k‖, so FAVOR+ key features cannot underflow to zero and make
    the normaliser's gradient overflow (training otherwise diverged to NaN); per position, so
    nothing crosses time. On for the shipped mvp models; False keeps older checkpoints exact.
    value_rotation: rotary values in the attention towers (mvp, mvt), in degrees per view of
    the base rate, 0 = off (older checkpoints). Channel pair i of each head's value turns by
    t · (i mod 7) · value_rotation at view t and the attention output turns back by the current
    view's angles, so a past view's features reach the current one rotated by the view offset
    alone (:func:`completion.towers.value_angles`). Without it a value is a linear map of its
    token plus the position code and cannot turn with the offset: the memory can carry only
    what does not change as the camera moves. 30 matches the simulated pans (30° a view).
    context: what a view's token is. "view": one token of D numbers per view, from the whole
    bottleneck volume (older checkpoints). "place": one token of D numbers per place of the g³
    bottleneck (g = G / 2**len(channels): 125 at G = 40) plus a learned code of the place; the
    sequence model relates every place of a view to every place of this and earlier views
    (attention, so the memory can carry a shape seen in one place to another, as when an object
    slides behind another) or runs one recurrence per place (LSTM), and its output is added to
    the bottleneck place by place. The Performer's memory keeps its size (H·M·E per layer).
    "both": the "view" path (bridge, tower) and beside it a "place" path of ``place_dim`` numbers
    per place (place_bridge, place_tower: same kind, heads and layers, M = place_features or
    n_features); their outputs are added. A "view" checkpoint warm-starts it exactly (the place
    path's output starts at 0).
    place_dim: D of the place path in "both" mode.
    place_window: with tokens per place, attention reads only the places within this many places
    (Chebyshev distance) of its own, in this and earlier views (0: every place). Local reads make
    the Performer's memory one (S, z) per place (P·H·M·E per layer, still independent of L).
    place_window_x: with place_window, how far a place reads along the grid's i axis (camera x,
    the image's horizontal) instead (0: place_window), so that a shape can travel across the
    image (an object sliding sideways, a pan) while the read stays local in height and depth.
    Changes no tensor: a checkpoint of the same place path loads.
    place_features: M of the place path in "both" mode (0: n_features).
    place_fine: numbers per place of the fine memory (0: none; attention kinds with tokens per
    place). Each place's 2×2×2 cells of the context encoder's next-finer feature volume (10³ at
    G = 40) are packed into place_fine numbers that the place path's first attention layer
    carries with the same attention weights as its values (extra value channels: the memory
    stays H·M·(E + place_fine/H) per place), and what it reads is unpacked to that level and
    added to the decoder's skip there, starting at zero. The 5³ bottleneck alone gives the
    decoder 8³-voxel blocks to draw a remembered shape from; this gives it the finer level too.
    shift_heads: heads of the shift memory (0: none; multi-view kinds): each view writes its finest
    context level into one memory per row along i as a Fourier series, in the frame of where it
    stands (a learned distribution over the cells it sees), and the current view reads it back in
    the frame of where it stands,
    so a shape moves along the image's x axis by any fraction of a 2-voxel cell
    (:mod:`completion.shift`). Its read is added to the decoder's (G/2)³ skip, starting at zero.
    shift_channels: Cv, channels a head writes. shift_freqs: M frequencies along i (0: G/2, the
    full resolution of that level). Memory: H·Cv·M·(G/2)²·2 + H·(G/2)² numbers.
    shift_decoded: the shift memory also writes the decoder's features at its (G/2)³ level (before
    the finest skip joins them, so a function of this view's frame and the context towers): the
    shape as the model completes it, not only the surface the view saw. Starts at zero, so a
    checkpoint without it warm-starts exactly.
    seed: weight initialisation and the initial FAVOR+ draw.
    """

    kind: ModelKind = "mvp"
    grid_size: int = 40
    channels: tuple[int, ...] = (16, 32, 64)
    conv_kernel: int = 3
    norm: Norm = "none"
    top_channels: int = 8
    token_channels: int = 16
    embed_dim: int = 256
    n_heads: int = 4
    n_layers: int = 1
    mlp_ratio: int = 2
    kernel: Kernel = "softmax"
    n_features: int = 128
    pos_encoding: PositionalEncoding = "sinusoidal"
    pos_base: float = 10000.0
    qk_norm: bool = False
    value_rotation: float = 0.0
    context: Context = "view"
    place_dim: int = 64
    place_window: int = 0
    place_window_x: int = 0
    place_features: int = 0
    place_fine: int = 0
    shift_heads: int = 0
    shift_channels: int = 8
    shift_freqs: int = 0
    shift_decoded: bool = False
    seed: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "channels", tuple(int(c) for c in self.channels))
        if self.kind not in MODEL_KINDS:
            raise ValueError(f"kind must be one of {MODEL_KINDS}, got {self.kind!r}")
        if self.kernel not in ("softmax", "relu"):
            raise ValueError(f"kernel must be 'softmax' or 'relu', got {self.kernel!r}")
        if self.norm not in get_args(Norm):
            raise ValueError(f"norm must be one of {get_args(Norm)}, got {self.norm!r}")
        if self.context not in get_args(Context):
            raise ValueError(f"context must be one of {get_args(Context)}, got {self.context!r}")
        if self.pos_encoding not in get_args(PositionalEncoding):
            raise ValueError(
                f"pos_encoding must be one of {get_args(PositionalEncoding)}, "
                f"got {self.pos_encoding!r}"
            )
        if not self.channels or any(c < 1 for c in self.channels):
            raise ValueError(
                f"channels must be a non-empty tuple of positive ints, got {self.channels}"
            )
        if self.conv_kernel not in (3, 4):
            raise ValueError(f"conv_kernel must be 3 or 4, got {self.conv_kernel}")
        step = 2 ** len(self.channels)
        if self.grid_size < step or self.grid_size % step:
            raise ValueError(
                f"grid_size {self.grid_size} must be a positive multiple of "
                f"2**len(channels) = {step}"
            )
        for name in (
            "embed_dim", "n_heads", "n_layers", "mlp_ratio", "n_features", "top_channels",
            "token_channels", "place_dim",
        ):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.place_window < 0 or self.place_features < 0:
            raise ValueError("place_window and place_features must be >= 0, got "
                             f"{self.place_window} and {self.place_features}")
        if self.place_window_x < 0 or (self.place_window_x and not self.place_window):
            raise ValueError("place_window_x needs place_window >= 1 and must be >= 0, got "
                             f"place_window {self.place_window}, place_window_x "
                             f"{self.place_window_x}")
        if self.place_fine < 0:
            raise ValueError(f"place_fine must be >= 0, got {self.place_fine}")
        if self.place_fine and (self.context == "view" or self.kind not in ("mvp", "mvt")
                                or len(self.channels) < 2 or self.place_fine % self.n_heads):
            raise ValueError("place_fine needs an attention model (mvp, mvt) with tokens per place "
                             "(context 'place' or 'both'), two U-Net levels or more, and a "
                             f"multiple of n_heads {self.n_heads}; got place_fine "
                             f"{self.place_fine}, kind {self.kind!r}, context {self.context!r}")
        if self.shift_heads < 0 or self.shift_channels < 1 or not (
                0 <= self.shift_freqs <= self.grid_size // 2):
            raise ValueError("shift_heads must be >= 0, shift_channels >= 1 and shift_freqs in "
                             f"[0, G/2 = {self.grid_size // 2}]; got {self.shift_heads}, "
                             f"{self.shift_channels}, {self.shift_freqs}")
        if self.shift_heads and (self.kind == "single_view" or len(self.channels) < 2):
            raise ValueError("shift_heads needs a multi-view model (a memory) with two U-Net "
                             f"levels or more, got kind {self.kind!r}, channels {self.channels}")
        if self.shift_decoded and not self.shift_heads:
            raise ValueError("shift_decoded needs the shift memory (shift_heads >= 1)")
        if self.place_window and self.context == "view":
            raise ValueError("place_window needs tokens per place (context 'place' or 'both')")
        if self.context == "both" and self.place_dim % (2 * self.n_heads):
            raise ValueError(f"place_dim {self.place_dim} must be divisible by 2 * n_heads "
                             f"{self.n_heads}")
        if self.embed_dim % self.n_heads:
            raise ValueError(
                f"embed_dim {self.embed_dim} must be divisible by n_heads {self.n_heads}"
            )
        object.__setattr__(self, "value_rotation", float(self.value_rotation))
        if not (math.isfinite(self.value_rotation) and 0 <= self.value_rotation <= 180):
            raise ValueError(f"value_rotation must be in [0, 180] degrees per view, "
                             f"got {self.value_rotation}")
        if self.value_rotation and (self.kind not in ("mvp", "mvt") or
                                    (self.embed_dim // self.n_heads) % 2):
            raise ValueError("value_rotation needs an attention model (mvp, mvt) with an even "
                             f"head size, got kind {self.kind!r}, head size "
                             f"{self.embed_dim // self.n_heads}")
        if self.pos_encoding == "sinusoidal" and self.embed_dim % 2:
            raise ValueError(f"sinusoidal encoding needs an even embed_dim, got {self.embed_dim}")
        if self.norm == "group" and any(c % _groups(c) for c in self.channels):
            raise ValueError(f"channels {self.channels} do not split into GroupNorm groups")

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


DEFAULT_CONFIGS: dict[str, ModelConfig] = {
    "single_view": ModelConfig(kind="single_view"),
    "mvp": ModelConfig(kind="mvp", kernel="softmax", qk_norm=True),
    "mvp_relu": ModelConfig(kind="mvp", kernel="relu", qk_norm=True),
    "mvp3": ModelConfig(kind="mvp", kernel="softmax", qk_norm=True),
    "mvp6": ModelConfig(kind="mvp", kernel="softmax", qk_norm=True),
    "mvt": ModelConfig(kind="mvt"),
    "lstm": ModelConfig(kind="lstm"),
}
"""Default config per shipped model name (mvp3/mvp6 differ from mvp only in training views)."""


def default_config(name: str, **overrides: Any) -> ModelConfig:
    """The default :class:`ModelConfig` for a model name (see :data:`DEFAULT_CONFIGS`)."""
    if name not in DEFAULT_CONFIGS:
        raise ValueError(f"unknown model name {name!r}; expected one of {sorted(DEFAULT_CONFIGS)}")
    return DEFAULT_CONFIGS[name].replace(**overrides)


def _groups(channels: int) -> int:
    """GroupNorm groups: 4 channels per group where possible."""
    return max(1, channels // 4)


# --------------------------------------------------------------------------------------------
# Shared encoder / decoder
# --------------------------------------------------------------------------------------------


class Encoder(nn.Module):
    """Down path of the 3-D U-Net, one frame at a time: (N, G, G, G) -> one feature volume per
    level, finest first: [(N, C0, G/2, G/2, G/2), (N, C1, G/4, …), …, (N, Cn, G/2^n, …)].

    Each level is a stride-2 conv (so nothing but the decoder's output layer runs at G³) and a
    same-size conv, each followed by ReLU (and GroupNorm per frame if ``norm="group"``).
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        k = config.conv_kernel
        self.levels = nn.ModuleList()
        c_in = 1
        for c_out in config.channels:
            self.levels.append(
                nn.Sequential(
                    *_conv(c_in, c_out, k, config.norm, stride=2),
                    *_conv(c_out, c_out, 3, config.norm),
                )
            )
            c_in = c_out

    def forward(self, grids: Tensor) -> list[Tensor]:
        # channels-last: oneDNN's 3-D convolutions with few channels run 5-15x faster on the CPU
        x = grids.unsqueeze(1).contiguous(memory_format=torch.channels_last_3d)
        features = []
        for level in self.levels:
            x = level(x)
            features.append(x)
        return features


class Decoder(nn.Module):
    """Up path of the 3-D U-Net: bottleneck volume + the local tower's skips + the raw input ->
    logits (N, G, G, G).

    Per level: a stride-2 transposed conv up, concatenation with the skip of that level from the
    current frame's encoder, a conv. At the top, a last transposed conv to G³, the raw input grid
    concatenated, and one conv to logits, so the observed surface reaches the output directly.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        chans = list(config.channels)
        self.bottom = nn.Sequential(*_conv(chans[-1], chans[-1], 3, config.norm))
        self.ups = nn.ModuleList()
        self.fuse = nn.ModuleList()
        for c_deep, c_skip in zip(chans[:0:-1], chans[-2::-1], strict=True):
            self.ups.append(nn.ConvTranspose3d(c_deep, c_skip, 2, stride=2))
            self.fuse.append(nn.Sequential(*_conv(2 * c_skip, c_skip, 3, config.norm)))
        self.top = nn.ConvTranspose3d(chans[0], config.top_channels, 2, stride=2)
        self.out = Conv3d(config.top_channels + 1, 1, 3, padding=1)

    def forward(self, bottom: Tensor, skips: list[Tensor], grids: Tensor) -> Tensor:
        return self.finish(self.rise(bottom, skips), skips[0], grids)

    def rise(self, bottom: Tensor, skips: list[Tensor]) -> Tensor:
        """Up to the finest level, before its skip joins: (N, C0, G/2, G/2, G/2). It does not
        depend on ``skips[0]``, so the shift memory can write it and add its read there."""
        x = self.bottom(bottom)
        if not self.ups:  # one level: the bottleneck is the finest level
            return x
        for up, fuse, skip in zip(self.ups[:-1], self.fuse[:-1], skips[-2:0:-1], strict=True):
            x = fuse(torch.cat((torch.relu(up(x)), skip), dim=1))
        return torch.relu(self.ups[-1](x))

    def finish(self, risen: Tensor, skip: Tensor, grids: Tensor) -> Tensor:
        """:meth:`rise`'s output and the finest skip -> logits (N, G, G, G)."""
        x = self.fuse[-1](torch.cat((risen, skip), dim=1)) if self.fuse else risen
        x = torch.relu(self.top(x))
        x = torch.cat((x, grids.unsqueeze(1).to(x.dtype)), dim=1)
        x = x.contiguous(memory_format=torch.channels_last_3d)
        return self.out(x).squeeze(1)  # (N, G, G, G)


def _conv(c_in: int, c_out: int, k: int, norm: str, *, stride: int = 1) -> list[nn.Module]:
    """Conv (padding 1: same size at stride 1, halved at stride 2), GroupNorm?, ReLU."""
    layers: list[nn.Module] = [Conv3d(c_in, c_out, k, stride=stride, padding=1)]
    if norm == "group":
        layers.append(nn.GroupNorm(_groups(c_out), c_out))
    layers.append(nn.ReLU())
    return layers


class Bridge(nn.Module):
    """Between the bottleneck volume and the context tower's tokens.

    ``token``: (N, Cn, g, g, g) -> (N, 1, D): a 1×1×1 conv to ``token_channels``, flattened, a
    dense layer (no activation, so the token can be negative for the attention). ``volume``:
    (N, 1, D) -> (N, Cn, g, g, g), the mirror, whose last layer starts at zero so that a model
    warm-started from Single-View weights begins exactly as that model.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        c, ct = config.channels[-1], config.token_channels
        self.g = config.grid_size // 2 ** len(config.channels)
        self.ct = ct
        self.reduce = Conv3d(c, ct, 1)
        self.to_token = nn.Linear(ct * self.g**3, config.embed_dim)
        self.from_token = nn.Linear(config.embed_dim, ct * self.g**3)
        self.expand = Conv3d(ct, c, 1)
        nn.init.zeros_(self.expand.weight)
        nn.init.zeros_(self.expand.bias)

    places = 1

    def token(self, bottom: Tensor) -> Tensor:
        return self.to_token(torch.relu(self.reduce(bottom)).flatten(1)).unsqueeze(1)

    def volume(self, token: Tensor) -> Tensor:
        g = self.g
        x = torch.relu(self.from_token(token.squeeze(1))).view(-1, self.ct, g, g, g)
        return self.expand(x)


class PlaceBridge(nn.Module):
    """Bridge for ``context="place"``: a token per place of the bottleneck volume.

    ``token``: (N, Cn, g, g, g) -> (N, P, D), P = g³ places in (i, j, k) order: a 1×1×1 conv to D
    channels plus a learned code per place (the 3-D position the attention needs to move a shape).
    ``volume``: (N, P, D) -> (N, Cn, g, g, g): per place a 1×1×1 conv, ReLU and a 1×1×1 conv that
    starts at zero (as in :class:`Bridge`).
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        c, d = config.channels[-1], config.embed_dim
        self.g = config.grid_size // 2 ** len(config.channels)
        self.places = self.g**3
        self.reduce = Conv3d(c, d, 1)
        self.place = nn.Parameter(torch.randn(self.places, d) * 0.5)
        self.lift = Conv3d(d, d, 1)
        self.expand = Conv3d(d, c, 1)
        nn.init.zeros_(self.expand.weight)
        nn.init.zeros_(self.expand.bias)
        self.fine = config.place_fine
        if self.fine:  # the next-finer level, 2×2×2 cells a place, in and out
            c_fine = config.channels[-2]
            self.fine_pack = Conv3d(c_fine, self.fine, 2, stride=2)
            self.fine_unpack = nn.ConvTranspose3d(self.fine, c_fine, 2, stride=2)
            nn.init.zeros_(self.fine_unpack.weight)
            nn.init.zeros_(self.fine_unpack.bias)

    def token(self, bottom: Tensor) -> Tensor:
        x = self.reduce(bottom).flatten(2).transpose(1, 2)  # (N, P, D)
        return x + self.place.to(x.dtype)

    def fine_token(self, finer: Tensor) -> Tensor:
        """(N, C, 2g, 2g, 2g) -> (N, P, place_fine): each place's cells packed."""
        return self.fine_pack(finer).flatten(2).transpose(1, 2)

    def fine_volume(self, fine: Tensor) -> Tensor:
        """(N, P, place_fine) -> (N, C, 2g, 2g, 2g), to add to the decoder's skip there."""
        g = self.g
        x = fine.transpose(1, 2).reshape(fine.shape[0], -1, g, g, g)
        return self.fine_unpack(x.contiguous(memory_format=torch.channels_last_3d))

    def volume(self, token: Tensor) -> Tensor:
        g = self.g
        x = token.transpose(1, 2).reshape(token.shape[0], -1, g, g, g)
        x = x.contiguous(memory_format=torch.channels_last_3d)
        return self.expand(torch.relu(self.lift(x)))


# --------------------------------------------------------------------------------------------
# The model
# --------------------------------------------------------------------------------------------


class CompletionModel(nn.Module):
    """One of the four kinds (``config.kind``); build with :func:`build_model`.

    ``forward(seq)`` (B, L, G, G, G) -> logits (B, L, G, G, G), causal.
    ``init_state(batch)`` -> state; ``step(state, frame)`` with frame (B, G, G, G) ->
    (logits (B, G, G, G), new state). Inputs may be float or bool occupancy.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.config = config
        generator = torch.Generator().manual_seed(config.seed)
        self.encoder = Encoder(config)
        self.decoder = Decoder(config)
        self.context_encoder: Encoder | None = None
        self.bridge: Bridge | PlaceBridge | None = None
        self.tower: AttentionTower | LSTMTower | None = None
        self.place_bridge: PlaceBridge | None = None
        self.place_tower: AttentionTower | LSTMTower | None = None
        if config.kind != "single_view":
            self.context_encoder = Encoder(config)
            self.bridge = PlaceBridge(config) if config.context == "place" else Bridge(config)
            self.tower = _tower(config, self.bridge.places, generator, prefix="")
            if config.context == "both":
                place = config.replace(embed_dim=config.place_dim, context="place",
                                       n_features=config.place_features or config.n_features)
                self.place_bridge = PlaceBridge(place)
                self.place_tower = _tower(place, self.place_bridge.places, generator,
                                          prefix="place.")
        # last, so the other modules draw the same initial weights with or without it
        self.shift_memory = ShiftMemory(config) if config.shift_heads else None

    def _paths(self) -> list[tuple[Bridge | PlaceBridge, AttentionTower | LSTMTower]]:
        """The context paths, (bridge, sequence model) each: none, one, or view and place."""
        pairs = [(self.bridge, self.tower), (self.place_bridge, self.place_tower)]
        return [(b, t) for b, t in pairs if b is not None and t is not None]

    # ---- input checks --------------------------------------------------------------------

    def _check_grids(self, x: Tensor, *, ndim: int, what: str) -> Tensor:
        g = self.config.grid_size
        if not isinstance(x, Tensor):
            raise ValueError(f"{what} must be a torch.Tensor, got {type(x).__name__}")
        if x.ndim != ndim or tuple(x.shape[-3:]) != (g, g, g):
            expected = "(B, L, G, G, G)" if ndim == 5 else "(B, G, G, G)"
            raise ValueError(f"{what} must be {expected} with G = {g}, got {tuple(x.shape)}")
        return x.to(self.decoder.out.weight.dtype)  # bool/uint8 occupancy, or another float

    # ---- parallel ------------------------------------------------------------------------

    def forward(
        self, seq: Tensor, *, local: Tensor | None = None, drop_view_path: Tensor | None = None
    ) -> Tensor:
        """``local``: what the local tower and the decoder's raw-input skip see instead of
        ``seq`` (same shape); training blanks views there so that the context tower must carry
        the shape (``completion.train --blank-local``). The context tower always sees ``seq``.
        ``drop_view_path``: (B,) bool, ``context="both"`` only: those sequences go without the
        per-view path, so that the place path must carry the memory (``--drop-view-path``).
        """
        seq = self._check_grids(seq, ndim=5, what="seq")
        b, n = seq.shape[:2]
        frames = seq.flatten(0, 1)  # (N, G, G, G)
        if local is not None:
            local = self._check_grids(local, ndim=5, what="local")
            if local.shape != seq.shape:
                raise ValueError(f"local must have seq's shape {tuple(seq.shape)}, "
                                 f"got {tuple(local.shape)}")
        local_frames = frames if local is None else local.flatten(0, 1)
        if drop_view_path is not None and (
            self.place_bridge is None or tuple(drop_view_path.shape) != (b,)
        ):
            raise ValueError("drop_view_path needs a model with context='both' and shape (B,) "
                             f"= ({b},), got {tuple(drop_view_path.shape)} for context "
                             f"{self.config.context!r}")
        skips = self.encoder(local_frames)  # local tower: this frame alone
        bottom = skips[-1]
        levels: list[Tensor] = []
        if self.context_encoder is not None:
            levels = self.context_encoder(frames)
            for bridge, tower in self._paths():
                tokens = bridge.token(levels[-1])
                tokens = tokens.view(b, n, *tokens.shape[1:])  # (B, L, P, D)
                fine = _fine_tokens(bridge, levels, (b, n))  # (B, L, P, F) or None
                with _full_precision(tokens):
                    if fine is None:
                        context = tower(tokens.float())  # (B, L, P, D)
                    else:
                        context, fine = tower(tokens.float(), extra=fine.float())
                volume = bridge.volume(context.flatten(0, 1)).to(bottom.dtype)
                if drop_view_path is not None and bridge is self.bridge:
                    keep = (~drop_view_path).repeat_interleave(n).to(volume.dtype)  # (N,)
                    volume = volume * keep.view(-1, 1, 1, 1, 1)
                bottom = bottom + volume
                if fine is not None:
                    skips = _add_fine(skips, bridge.fine_volume(fine.flatten(0, 1)))
        risen = self.decoder.rise(bottom, skips)
        if self.shift_memory is not None:
            decoded = risen if self.config.shift_decoded else None
            skips = _add_shift(skips, self.shift_memory(levels[0], frames, (b, n), decoded))
        logits = self.decoder.finish(risen, skips[0], local_frames)  # (N, G, G, G)
        return logits.view(seq.shape)

    def _context_step(
        self, frame: Tensor, state: State
    ) -> tuple[list[Tensor], list[Tensor], Tensor, State]:
        """One view through the context tower: each path's bottleneck volume (B, Cn, g, g, g),
        the fine volumes of the paths with ``place_fine`` (B, Cn-1, 2g, 2g, 2g), the context
        encoder's finest level (B, C0, G/2, G/2, G/2) for the shift memory, and the new state of
        the sequence models."""
        assert self.context_encoder is not None
        levels = self.context_encoder(frame)
        volumes, fines, new = [], [], {}
        for bridge, tower in self._paths():
            tokens = bridge.token(levels[-1])
            fine = _fine_tokens(bridge, levels, None)
            with _full_precision(tokens):
                if fine is None:
                    context, entries = tower.step(tokens.float(), state["t"], state)
                else:
                    (context, fine), entries = tower.step(tokens.float(), state["t"], state,
                                                          extra=fine.float())
            volumes.append(bridge.volume(context))
            if fine is not None:
                fines.append(bridge.fine_volume(fine))
            new |= entries
        return volumes, fines, levels[0], new

    # ---- streaming -----------------------------------------------------------------------

    def init_state(self, batch: int) -> State:
        """State before any view: {"t": 0-d int64} plus the tower's memory."""
        if batch < 1:
            raise ValueError(f"batch must be >= 1, got {batch}")
        device = self.decoder.out.weight.device
        state: State = {"t": torch.zeros((), dtype=torch.int64, device=device)}
        for _, tower in self._paths():
            state |= tower.init_state(batch, device=device)
        if self.shift_memory is not None:
            state |= self.shift_memory.init_state(batch, device=device)
        return state

    def step(self, state: State, frame: Tensor) -> tuple[Tensor, State]:
        """Consume one view: frame (B, G, G, G) -> (logits (B, G, G, G), new state).

        The given state is not modified, so it can be kept and stepped again.
        """
        logits, new = self._step(state, frame, decode=True)
        assert logits is not None
        return logits, new

    def advance(self, state: State, frame: Tensor) -> State:
        """Consume one view without decoding it: the state :meth:`step` would return, cheaper.

        For catching up on views whose completion is not needed (only the latest one usually is).
        """
        return self._step(state, frame, decode=False)[1]

    def _step(self, state: State, frame: Tensor, *, decode: bool) -> tuple[Tensor | None, State]:
        """:meth:`step`, without the decoder's last levels unless ``decode`` (and without the
        local tower too unless the shift memory writes what the decoder makes of the view)."""
        frame = self._check_grids(frame, ndim=4, what="frame")
        self._check_state(state, batch=frame.shape[0])
        new: State = {}
        volumes: list[Tensor] = []
        fines: list[Tensor] = []
        if self.context_encoder is not None:
            volumes, fines, level, new = self._context_step(frame, state)
        t = {"t": state["t"] + 1}
        if not (decode or self.config.shift_decoded):
            if self.shift_memory is not None:
                new |= self.shift_memory.step(level, frame, state)[1]
            return None, new | t
        skips = self.encoder(frame)
        bottom = skips[-1]
        for volume in volumes:
            bottom = bottom + volume.to(bottom.dtype)
        for fine in fines:
            skips = _add_fine(skips, fine)
        risen = self.decoder.rise(bottom, skips)
        if self.shift_memory is not None:
            decoded = risen if self.config.shift_decoded else None
            shift, entries = self.shift_memory.step(level, frame, state, decoded)
            new |= entries
            skips = _add_shift(skips, shift)
        if not decode:
            return None, new | t
        return self.decoder.finish(risen, skips[0], frame), new | t

    def _check_state(self, state: State, *, batch: int) -> None:
        """Keys and shapes as from ``init_state(batch)``; a KV cache may differ along T."""
        reference = self.init_state(batch)
        if not isinstance(state, Mapping) or state.keys() != reference.keys():
            got = sorted(state.keys()) if isinstance(state, Mapping) else type(state).__name__
            raise ValueError(f"state must have keys {sorted(reference)}, got {got}")
        for name, ref in reference.items():
            shape, want = list(state[name].shape), list(ref.shape)
            if name.endswith(KV_CACHE_SUFFIXES) and len(shape) == 4:
                shape[2] = want[2] = 0  # (B, H, T, E): T grows with the views
            if shape != want:
                raise ValueError(
                    f"state {name!r} has shape {tuple(state[name].shape)}, expected "
                    f"{tuple(ref.shape)} for batch {batch} (was it made by this model?)"
                )

    def redraw_features(self, *, seed: int) -> None:
        """Redraw every FAVOR+ projection from ``seed`` (training only; no-op without any)."""
        generator = torch.Generator().manual_seed(seed)
        for module in self.modules():
            if isinstance(module, FeatureMap):
                module.redraw(generator=generator)

    def n_params(self) -> int:
        """Trainable parameters (the FAVOR+ buffers are not counted)."""
        return sum(p.numel() for p in self.parameters() if p.requires_grad)


def _tower(
    config: ModelConfig, places: int, generator: torch.Generator, *, prefix: str
) -> AttentionTower | LSTMTower:
    """The sequence model of ``config.kind`` over ``places`` tokens a view; its state keys
    start with ``prefix``."""
    if config.kind == "lstm":
        return LSTMTower(config, places=places, prefix=prefix)
    mechanism = "performer" if config.kind == "mvp" else "exact"
    return AttentionTower(config, mechanism=mechanism, generator=generator, prefix=prefix)


def _fine_tokens(
    bridge: Bridge | PlaceBridge, levels: list[Tensor], batch: tuple[int, int] | None
) -> Tensor | None:
    """A place bridge's fine tokens from the context encoder's next-finer level (``place_fine``),
    (N, P, F) or with ``batch`` = (B, L) (B, L, P, F); None without fine memory."""
    if not getattr(bridge, "fine", 0):
        return None
    fine = bridge.fine_token(levels[-2])
    return fine if batch is None else fine.view(*batch, *fine.shape[1:])


def _add_fine(skips: list[Tensor], fine: Tensor) -> list[Tensor]:
    """The local tower's skips with ``fine`` added to the next-finer level's (a new list)."""
    return [*skips[:-2], skips[-2] + fine.to(skips[-2].dtype), skips[-1]]


def _add_shift(skips: list[Tensor], shift: Tensor) -> list[Tensor]:
    """The local tower's skips with the shift memory's read added to the finest level's."""
    return [skips[0] + shift.to(skips[0].dtype), *skips[1:]]


def _full_precision(x: Tensor):
    """The sequence models run in fp32 even under bf16 autocast (FAVOR+ features and the
    attention normaliser need the range); the convolutions around them may run in bf16."""
    return torch.autocast(device_type=x.device.type, enabled=False)


def build_model(config: ModelConfig) -> CompletionModel:
    """A freshly initialised model; deterministic given ``config.seed``."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        return CompletionModel(config)


# --------------------------------------------------------------------------------------------
# State and checkpoint serialisation
# --------------------------------------------------------------------------------------------


def state_to_bytes(state: State) -> bytes:
    """Serialise a streaming state exactly (torch.save of CPU tensors, compact storages)."""
    if not isinstance(state, Mapping) or not all(isinstance(v, Tensor) for v in state.values()):
        raise ValueError("state must be a dict[str, Tensor]")
    buffer = io.BytesIO()
    torch.save({k: v.detach().to("cpu").clone().contiguous() for k, v in state.items()}, buffer)
    return buffer.getvalue()


def state_from_bytes(data: bytes, *, device: torch.device | str = "cpu") -> State:
    """Inverse of :func:`state_to_bytes` (``torch.load(weights_only=True)``)."""
    state = torch.load(io.BytesIO(data), map_location=device, weights_only=True)
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, Tensor) for k, v in state.items()
    ):
        raise ValueError("bytes do not hold a dict[str, Tensor] state")
    return state


def state_nbytes(state: State) -> int:
    """Raw tensor payload of a state in bytes (without serialisation overhead)."""
    return sum(v.numel() * v.element_size() for v in state.values())


def _check_plain(value: Any, path: str) -> None:
    """Raise unless ``value`` is loadable by ``torch.load(weights_only=True)`` as plain data."""
    if value is None or isinstance(value, (bool, int, float, str, Tensor)):
        return
    if isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            _check_plain(item, f"{path}[{i}]")
        return
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, (str, int)):
                raise ValueError(f"checkpoint key {path}[{key!r}] must be str or int")
            _check_plain(item, f"{path}[{key!r}]")
        return
    raise ValueError(
        f"checkpoint entry {path} is a {type(value).__name__}; only plain data "
        "(dict, list, str, int, float, bool, None, Tensor) can be loaded with weights_only=True"
    )


def save_checkpoint(model: CompletionModel, path: str | os.PathLike[str], /, **extra: Any) -> None:
    """Write ``{"format", "version", "config", "grid", "state_dict", **extra}`` to ``path``.

    ``extra`` holds plain data only (e.g. epoch, metrics, threshold, optimizer state dict);
    ``grid=...`` overrides :data:`GRID_CONVENTION`.
    """
    reserved = {"format", "version", "config", "state_dict"} & extra.keys()
    if reserved:
        raise ValueError(f"extra checkpoint entries may not be named {sorted(reserved)}")
    payload: dict[str, Any] = {
        "format": CHECKPOINT_FORMAT,
        "version": CHECKPOINT_VERSION,
        "config": model.config.to_dict(),
        "grid": GRID_CONVENTION,
        **extra,
    }
    _check_plain(payload, "checkpoint")
    payload["state_dict"] = {k: v.detach().cpu() for k, v in model.state_dict().items()}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    torch.save(payload, tmp)
    os.replace(tmp, path)


def read_checkpoint(
    path: str | os.PathLike[str], *, map_location: torch.device | str = "cpu"
) -> dict[str, Any]:
    """The raw checkpoint dict (config as a plain dict, state_dict, extras), validated."""
    payload = torch.load(Path(path), map_location=map_location, weights_only=True)
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path} is not a completion checkpoint (format {CHECKPOINT_FORMAT!r})")
    if payload.get("version") != CHECKPOINT_VERSION:
        raise ValueError(
            f"{path} has checkpoint version {payload.get('version')}, expected {CHECKPOINT_VERSION}"
        )
    return payload


def load_checkpoint(
    path: str | os.PathLike[str], *, map_location: torch.device | str = "cpu"
) -> CompletionModel:
    """Rebuild the model stored at ``path`` (in eval mode); needs nothing but the file.

    ``model.threshold`` is the decision threshold stored with the weights (chosen on validation
    data by ``python -m completion.train select-threshold``; 0.5 if the file has none) and
    ``model.name`` the checkpoint's name.
    """
    payload = read_checkpoint(path, map_location=map_location)
    model = build_model(ModelConfig.from_dict(payload["config"]))  # leaves the global RNG alone
    model.load_state_dict(payload["state_dict"])  # casts e.g. fp16 weights to the fp32 model
    model.threshold = float(payload.get("threshold", 0.5))
    model.name = str(payload.get("name", Path(path).stem))
    return model.to(map_location).eval()


def available_weights() -> list[str]:
    """Names of the shipped weights in ``completion/weights/``."""
    return sorted(p.stem for p in WEIGHTS_DIR.glob("*.pt"))


def load_model(
    name_or_path: str | os.PathLike[str], *, map_location: torch.device | str = "cpu"
) -> CompletionModel:
    """Load shipped weights by name (``"mvp"`` -> ``completion/weights/mvp.pt``) or a file path."""
    text = os.fspath(name_or_path)
    path = Path(text)
    if not path.suffix and os.sep not in text and "/" not in text:
        path = WEIGHTS_DIR / f"{text}.pt"
        if not path.is_file():
            raise FileNotFoundError(
                f"no shipped weights named {text!r} in {WEIGHTS_DIR}; "
                f"available: {available_weights() or 'none'}"
            )
    elif not path.is_file():
        raise FileNotFoundError(f"checkpoint {path} does not exist")
    return load_checkpoint(path, map_location=map_location)
