"""The context towers of the multi-view models: how a frame sees the past.

A view's token gets a sinusoidal encoding of the view index and goes through causal Transformer
blocks, Performer (FAVOR+ or ReLU kernel, constant-size memory) for ``mvp``, exact softmax
attention with a key/value cache for ``mvt``, or an LSTM for ``lstm``. The attention towers may
turn each value by its view index (rotary values, ``ModelConfig.value_rotation``), so that the
memory can hand a past view's features to the current view rotated by the view offset. Each has
a parallel ``forward`` over (B, L, P, D) and a streaming ``step`` over (B, P, D) with a flat
state dict; both give the same numbers. P is the number of tokens a view has (1 for every model
here: :class:`completion.model.Bridge`); attention is causal over views and full within one.
Shapes use the axis letters of :mod:`completion.model`.
"""
from __future__ import annotations

import math
from typing import Literal

import torch
from torch import Tensor, nn

from completion.config import ModelConfig
from completion.performer import (
    FeatureMap,
    block_causal_linear_attention,
    block_causal_softmax_attention,
    block_linear_attention_step,
    init_linear_attention_state,
)

State = dict[str, Tensor]

POSITION_BASE = 10000.0
"""Base of the sinusoidal encoding of the view index (Vaswani et al. 2017)."""


def sinusoidal_encoding(positions: Tensor, dim: int, *, base: float = POSITION_BASE) -> Tensor:
    """Sinusoidal encoding of view indices: positions (...,) int -> (..., dim) float32.

    Channel 2i is sin(t·base^(-2i/dim)), channel 2i+1 is cos of the same (Vaswani et al. 2017).
    """
    half = torch.arange(dim // 2, dtype=torch.float32, device=positions.device)
    freqs = torch.exp(-math.log(base) * 2.0 * half / dim)  # (dim/2,)
    angles = positions.to(torch.float32).unsqueeze(-1) * freqs  # (..., dim/2)
    return torch.stack((angles.sin(), angles.cos()), dim=-1).flatten(-2)


#: Rotary values: channel pair i of a head turns at ``i % VALUE_HARMONICS`` times the base rate.
VALUE_HARMONICS = 7


def value_angles(positions: Tensor, head_dim: int, degrees_per_view: float) -> Tensor:
    """Angles of the rotary values: positions (...,) int -> (..., E/2) float32 radians.

    Pair i turns by t · (i mod 7) · degrees_per_view: harmonics 0 (content that does not turn
    with the view, such as size) to 6 of one rotation rate, as the features of a shape turning
    about one axis transform (the irreducible representations of SO(2)).
    """
    harmonic = torch.arange(head_dim // 2, device=positions.device) % VALUE_HARMONICS
    rate = harmonic.to(torch.float32) * math.radians(degrees_per_view)  # (E/2,)
    return positions.to(torch.float32).unsqueeze(-1) * rate


def rotate_pairs(x: Tensor, angles: Tensor) -> Tensor:
    """Rotate channel pairs (2i, 2i+1) of x (..., E) by angles (..., E/2) (broadcast)."""
    even, odd = x[..., 0::2], x[..., 1::2]
    cos, sin = angles.cos().to(x.dtype), angles.sin().to(x.dtype)
    return torch.stack((even * cos - odd * sin, even * sin + odd * cos), dim=-1).flatten(-2)


class CausalSelfAttention(nn.Module):
    """Multi-head causal self-attention over views, Performer (linear) or exact softmax.

    ``mechanism="performer"``: φ-features with a constant-size memory S (B, H, M, E),
    z (B, H, M). ``mechanism="exact"``: softmax(q·k/√E) with a key/value cache (B, H, T, E).

    With ``config.value_rotation`` (degrees per view, 0 = off) each value is rotated by its own
    view's angles (:func:`value_angles`) before it enters the memory and the output is rotated
    back by the current view's, so view s's value reaches view t turned by the offset t − s
    alone. The memory keeps its size; the angles need only the view index.
    """

    def __init__(
        self,
        config: ModelConfig,
        *,
        mechanism: Literal["performer", "exact"],
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        if mechanism not in ("performer", "exact"):
            raise ValueError(f"mechanism must be 'performer' or 'exact', got {mechanism!r}")
        self.mechanism = mechanism
        self.n_heads = config.n_heads
        self.head_dim = config.embed_dim // config.n_heads
        self.qkv = nn.Linear(config.embed_dim, 3 * config.embed_dim)
        self.out = nn.Linear(config.embed_dim, config.embed_dim)
        self.qk_norm = config.qk_norm
        self.value_rotation = config.value_rotation
        self.features: FeatureMap | None = None
        if mechanism == "performer":
            self.features = FeatureMap(
                self.head_dim,
                kernel=config.kernel,
                n_features=config.n_features,
                generator=generator,
            )

    def _heads(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """x (..., D) -> q, k, v each (..., H, E)."""
        q, k, v = self.qkv(x).chunk(3, dim=-1)
        shape = (*x.shape[:-1], self.n_heads, self.head_dim)
        q, k, v = q.view(shape), k.view(shape), v.view(shape)
        if self.qk_norm:  # per position and head: no statistic crosses views
            q = nn.functional.layer_norm(q, (self.head_dim,))
            k = nn.functional.layer_norm(k, (self.head_dim,))
        return q, k, v

    def _angles(self, positions: Tensor) -> Tensor | None:
        if not self.value_rotation:
            return None
        return value_angles(positions, self.head_dim, self.value_rotation)

    def forward(self, x: Tensor) -> Tensor:
        """Parallel form: x (B, L, P, D) -> (B, L, P, D)."""
        q, k, v = (t.permute(0, 3, 1, 2, 4) for t in self._heads(x))  # (B, H, L, P, E)
        angles = self._angles(torch.arange(x.shape[1], device=x.device))  # (L, E/2)
        if angles is not None:
            angles = angles.unsqueeze(-2)  # (L, 1, E/2): one turn per view, every token
            v = rotate_pairs(v, angles)
        if self.features is not None:
            phi_q, phi_k = self.features(q, is_query=True), self.features(k, is_query=False)
            y = block_causal_linear_attention(phi_q, phi_k, v)
        else:
            y = block_causal_softmax_attention(q, k, v)
        if angles is not None:
            y = rotate_pairs(y, -angles)
        return self.out(y.to(x.dtype).permute(0, 2, 3, 1, 4).flatten(3))  # (B, L, P, D)

    def init_state(self, batch: int, *, device: torch.device, prefix: str) -> State:
        if self.features is not None:
            s, z = init_linear_attention_state(
                (batch, self.n_heads), self.features.n_features, self.head_dim, device=device
            )
            return {f"{prefix}S": s, f"{prefix}z": z}
        empty = torch.zeros(batch, self.n_heads, 0, self.head_dim, device=device)
        return {f"{prefix}k": empty, f"{prefix}v": empty.clone()}

    def step(self, x: Tensor, t: Tensor, state: State, *, prefix: str) -> tuple[Tensor, State]:
        """Streaming form: x (B, P, D), t 0-d view index -> (B, P, D) and this layer's new
        state entries."""
        q, k, v = (u.transpose(1, 2) for u in self._heads(x))  # (B, H, P, E)
        angles = self._angles(t)  # (E/2,)
        if angles is not None:
            v = rotate_pairs(v, angles)
        if self.features is not None:
            phi_q, phi_k = self.features(q, is_query=True), self.features(k, is_query=False)
            s, z = state[f"{prefix}S"], state[f"{prefix}z"]
            y, s, z = block_linear_attention_step(phi_q, phi_k, v, s, z)
            new = {f"{prefix}S": s, f"{prefix}z": z}
        else:
            # the cache grows by P keys per view: (B, H, T·P, E)
            keys = torch.cat((state[f"{prefix}k"], k.to(torch.float32)), dim=2)
            values = torch.cat((state[f"{prefix}v"], v.to(torch.float32)), dim=2)
            scores = q.to(torch.float32) @ keys.transpose(-1, -2)  # (B, H, P, T·P)
            weights = torch.softmax(scores * self.head_dim**-0.5, dim=-1)
            y = weights @ values  # (B, H, P, E)
            new = {f"{prefix}k": keys, f"{prefix}v": values}
        if angles is not None:
            y = rotate_pairs(y, -angles)
        return self.out(y.to(x.dtype).transpose(1, 2).flatten(2)), new


class Block(nn.Module):
    """Pre-LayerNorm Transformer block: x + Attn(LN x), then + MLP(LN ·) with ReLU."""

    def __init__(
        self,
        config: ModelConfig,
        *,
        mechanism: Literal["performer", "exact"],
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        d = config.embed_dim
        self.norm1 = nn.LayerNorm(d)
        self.attn = CausalSelfAttention(config, mechanism=mechanism, generator=generator)
        self.norm2 = nn.LayerNorm(d)
        self.mlp = nn.Sequential(
            nn.Linear(d, config.mlp_ratio * d), nn.ReLU(), nn.Linear(config.mlp_ratio * d, d)
        )

    def forward(self, x: Tensor) -> Tensor:
        """(B, L, P, D) -> (B, L, P, D)."""
        x = x + self.attn(self.norm1(x))
        return x + self.mlp(self.norm2(x))

    def step(self, x: Tensor, t: Tensor, state: State, *, prefix: str) -> tuple[Tensor, State]:
        a, new = self.attn.step(self.norm1(x), t, state, prefix=prefix)  # (B, P, D)
        x = x + a
        return x + self.mlp(self.norm2(x)), new


class AttentionTower(nn.Module):
    """Positional encoding of the view index, causal Transformer blocks, final LayerNorm."""

    def __init__(
        self,
        config: ModelConfig,
        *,
        mechanism: Literal["performer", "exact"],
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        self.embed_dim = config.embed_dim
        self.blocks = nn.ModuleList(
            Block(config, mechanism=mechanism, generator=generator)
            for _ in range(config.n_layers)
        )
        self.norm = nn.LayerNorm(config.embed_dim)

    def _position(self, x: Tensor, positions: Tensor) -> Tensor:
        pe = sinusoidal_encoding(positions, self.embed_dim)
        return x + pe.unsqueeze(-2).to(x.dtype)  # the same code for every token of a view

    def forward(self, x: Tensor) -> Tensor:
        """(B, L, P, D) -> (B, L, P, D)."""
        x = self._position(x, torch.arange(x.shape[1], device=x.device))
        for block in self.blocks:
            x = block(x)
        return self.norm(x)

    def init_state(self, batch: int, *, device: torch.device) -> State:
        state: State = {}
        for i, block in enumerate(self.blocks):
            state |= block.attn.init_state(batch, device=device, prefix=f"layer{i}.")
        return state

    def step(self, x: Tensor, t: Tensor, state: State) -> tuple[Tensor, State]:
        """x (B, P, D), t 0-d view index -> (B, P, D), new tower state."""
        x = self._position(x, t.expand(x.shape[0]))
        new: State = {}
        for i, block in enumerate(self.blocks):
            x, entries = block.step(x, t, state, prefix=f"layer{i}.")
            new |= entries
        return self.norm(x), new


class LSTMTower(nn.Module):
    """LSTM over the views' tokens, one recurrence per token (shared weights); no positional
    encoding: the recurrence orders the views."""

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.n_layers = config.n_layers
        self.dim = config.embed_dim
        self.lstm = nn.LSTM(config.embed_dim, config.embed_dim, config.n_layers, batch_first=True)

    def forward(self, x: Tensor) -> Tensor:  # (B, L, P, D) -> (B, L, P, D)
        b, n, p, d = x.shape
        y = self.lstm(x.transpose(1, 2).reshape(b * p, n, d))[0]  # (B·P, L, D)
        return y.view(b, p, n, d).transpose(1, 2)

    def init_state(self, batch: int, *, device: torch.device) -> State:
        h = torch.zeros(self.n_layers, batch, self.dim, device=device)
        return {"lstm.h": h, "lstm.c": h.clone()}

    def step(self, x: Tensor, t: Tensor, state: State) -> tuple[Tensor, State]:
        b, p, d = x.shape
        y, (h, c) = self.lstm(x.reshape(b * p, 1, d), (state["lstm.h"], state["lstm.c"]))
        return y.view(b, p, d), {"lstm.h": h, "lstm.c": c}
