"""The context towers of the multi-view models: how a frame sees the past.

A view's tokens (one, or one per place of the bottleneck volume: ``ModelConfig.context``) get a
sinusoidal encoding of the view index and go through causal Transformer blocks, Performer
(FAVOR+ or ReLU kernel, constant-size memory) for ``mvp``, exact softmax attention with a
key/value cache for ``mvt``, or an LSTM for ``lstm``. The attention towers may turn each value by
its view index (rotary values, ``ModelConfig.value_rotation``), so that the memory can hand a
past view's features to the current view rotated by the view offset. Each has a parallel
``forward`` over (B, L, P, D) and a streaming ``step`` over (B, P, D) with a flat state dict; both
give the same numbers. P is the number of tokens per view: attention is causal over views and full
within one (a place reads every place of this and earlier views, or with ``place_window`` only the
places near it); the LSTM runs one recurrence per place. Shapes use the axis letters of
:mod:`completion.model`.
"""
from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal

import torch
from torch import Tensor, nn

from completion.performer import (
    FeatureMap,
    block_causal_linear_attention,
    block_causal_softmax_attention,
    block_linear_attention_step,
    init_linear_attention_state,
    local_causal_linear_attention,
    local_linear_attention_step,
    place_neighbours,
)

if TYPE_CHECKING:
    from completion.model import ModelConfig

State = dict[str, Tensor]


def sinusoidal_encoding(positions: Tensor, dim: int, *, base: float = 10000.0) -> Tensor:
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

    ``carries_fine`` (the first layer of a place path with ``config.place_fine``): each head's
    values get Ex = place_fine / H extra channels, the fine memory's tokens, read with the same
    weights (so the memory is (B, H, P, M, E + Ex)); ``forward`` and ``step`` take them as
    ``extra`` and return what they read beside the output.
    """

    def __init__(
        self,
        config: ModelConfig,
        *,
        mechanism: Literal["performer", "exact"],
        generator: torch.Generator | None = None,
        carries_fine: bool = False,
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
        # fine memory (config.place_fine): extra value channels per head, read with the same
        # attention weights as the values, not rotated, returned beside the output
        self.extra = 0
        if carries_fine and config.context == "place":
            self.extra = config.place_fine // config.n_heads
        # with a token per place: attend only within place_window places (0: everywhere)
        self.side = config.grid_size // 2 ** len(config.channels)
        self.window: int | tuple[int, int, int] = 0
        if config.context == "place" and config.place_window:
            w = config.place_window
            self.window = (config.place_window_x, w, w) if config.place_window_x else w
        # exact attention's (P, P) mask of the places each place may read; built once
        near = place_neighbours(self.side, self.window) if self.window else None
        self.register_buffer("near", near, persistent=False)
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

    def _with_extra(self, v: Tensor, extra: Tensor | None, heads_at: int) -> Tensor:
        """v with the extra value channels appended (``extra`` (..., H·Ex) split into heads and
        moved like v's head axis, which sits at ``heads_at``)."""
        if (extra is None) != (not self.extra):
            raise ValueError(f"this attention takes {self.extra} extra value channels per head "
                             f"(place_fine); got {'none' if extra is None else 'some'}")
        if extra is None:
            return v
        e = extra.view(*extra.shape[:-1], self.n_heads, self.extra).movedim(-2, heads_at)
        return torch.cat((v, e.to(v.dtype)), dim=-1)

    def _split_extra(self, y: Tensor) -> tuple[Tensor, Tensor | None]:
        if not self.extra:
            return y, None
        return y[..., : self.head_dim], y[..., self.head_dim :]

    def forward(self, x: Tensor, extra: Tensor | None = None) -> Tensor | tuple[Tensor, Tensor]:
        """Parallel form: x (B, L, P, D) -> (B, L, P, D); with ``extra`` (B, L, P, H·Ex) also
        what the attention reads of it, (B, L, P, H·Ex)."""
        q, k, v = (t.permute(0, 3, 1, 2, 4) for t in self._heads(x))  # (B, H, L, P, E)
        angles = self._angles(torch.arange(x.shape[1], device=x.device))  # (L, E/2)
        if angles is not None:
            angles = angles.unsqueeze(-2)  # (L, 1, E/2): one turn per view, every place
            v = rotate_pairs(v, angles)
        v = self._with_extra(v, extra, 1)  # (B, H, L, P, E + Ex)
        if self.features is not None:
            phi_q, phi_k = self.features(q, is_query=True), self.features(k, is_query=False)
            if self.window:
                y = local_causal_linear_attention(
                    phi_q, phi_k, v, side=self.side, window=self.window
                )
            else:
                y = block_causal_linear_attention(phi_q, phi_k, v)
        else:
            y = block_causal_softmax_attention(q, k, v, near=self.near)
        y, y_extra = self._split_extra(y)
        if angles is not None:
            y = rotate_pairs(y, -angles)
        y = self.out(y.to(x.dtype).permute(0, 2, 3, 1, 4).flatten(3))  # (B, L, P, D)
        if y_extra is None:
            return y
        return y, y_extra.permute(0, 2, 3, 1, 4).flatten(3)

    def init_state(self, batch: int, *, device: torch.device, prefix: str) -> State:
        if self.features is not None:
            places = (self.side**3,) if self.window else ()  # one memory per place
            s, z = init_linear_attention_state(
                (batch, self.n_heads, *places), self.features.n_features,
                self.head_dim + self.extra, device=device,
            )
            return {f"{prefix}S": s, f"{prefix}z": z}
        empty = torch.zeros(batch, self.n_heads, 0, self.head_dim, device=device)
        values = torch.zeros(batch, self.n_heads, 0, self.head_dim + self.extra, device=device)
        return {f"{prefix}k": empty, f"{prefix}v": values}

    def step(
        self, x: Tensor, t: Tensor, state: State, *, prefix: str, extra: Tensor | None = None
    ) -> tuple[Tensor | tuple[Tensor, Tensor], State]:
        """Streaming form: x (B, P, D), t 0-d view index -> (B, P, D) (with ``extra``
        (B, P, H·Ex): and what is read of it, as in :meth:`forward`) and this layer's new
        state entries."""
        q, k, v = (u.transpose(1, 2) for u in self._heads(x))  # (B, H, P, E)
        angles = self._angles(t)  # (E/2,)
        if angles is not None:
            v = rotate_pairs(v, angles)
        v = self._with_extra(v, extra, 1)  # (B, H, P, E + Ex)
        if self.features is not None:
            phi_q, phi_k = self.features(q, is_query=True), self.features(k, is_query=False)
            s, z = state[f"{prefix}S"], state[f"{prefix}z"]
            if self.window:
                y, s, z = local_linear_attention_step(
                    phi_q, phi_k, v, s, z, side=self.side, window=self.window
                )
            else:
                y, s, z = block_linear_attention_step(phi_q, phi_k, v, s, z)
            new = {f"{prefix}S": s, f"{prefix}z": z}
        else:
            # the cache grows by P keys per view: (B, H, T·P, E)
            keys = torch.cat((state[f"{prefix}k"], k.to(torch.float32)), dim=2)
            values = torch.cat((state[f"{prefix}v"], v.to(torch.float32)), dim=2)
            scores = q.to(torch.float32) @ keys.transpose(-1, -2)  # (B, H, P, T·P)
            if self.near is not None:
                far = ~self.near.repeat(1, keys.shape[2] // self.near.shape[0])
                scores = scores.masked_fill(far, float("-inf"))
            weights = torch.softmax(scores * self.head_dim**-0.5, dim=-1)
            y = weights @ values  # (B, H, P, E)
            new = {f"{prefix}k": keys, f"{prefix}v": values}
        y, y_extra = self._split_extra(y)
        if angles is not None:
            y = rotate_pairs(y, -angles)
        y = self.out(y.to(x.dtype).transpose(1, 2).flatten(2))
        if y_extra is None:
            return y, new
        return (y, y_extra.transpose(1, 2).flatten(2)), new


class Block(nn.Module):
    """Pre-LayerNorm Transformer block: x + Attn(LN x), then + MLP(LN ·) with ReLU."""

    def __init__(
        self,
        config: ModelConfig,
        *,
        mechanism: Literal["performer", "exact"],
        generator: torch.Generator | None = None,
        carries_fine: bool = False,
    ) -> None:
        super().__init__()
        d = config.embed_dim
        self.norm1 = nn.LayerNorm(d)
        self.attn = CausalSelfAttention(config, mechanism=mechanism, generator=generator,
                                        carries_fine=carries_fine)
        self.norm2 = nn.LayerNorm(d)
        self.mlp = nn.Sequential(
            nn.Linear(d, config.mlp_ratio * d), nn.ReLU(), nn.Linear(config.mlp_ratio * d, d)
        )

    def forward(self, x: Tensor, extra: Tensor | None = None) -> tuple[Tensor, Tensor | None]:
        """(B, L, P, D) -> (B, L, P, D), and what the attention read of ``extra`` (or None)."""
        a = self.attn(self.norm1(x), extra)
        a, read = a if extra is not None else (a, None)
        x = x + a
        return x + self.mlp(self.norm2(x)), read

    def step(
        self, x: Tensor, t: Tensor, state: State, *, prefix: str, extra: Tensor | None = None
    ) -> tuple[Tensor, Tensor | None, State]:
        a, new = self.attn.step(self.norm1(x), t, state, prefix=prefix, extra=extra)  # (B, P, D)
        a, read = a if extra is not None else (a, None)
        x = x + a
        return x + self.mlp(self.norm2(x)), read, new


class AttentionTower(nn.Module):
    """Positional encoding of the view index, causal Transformer blocks, final LayerNorm."""

    def __init__(
        self,
        config: ModelConfig,
        *,
        mechanism: Literal["performer", "exact"],
        generator: torch.Generator | None = None,
        prefix: str = "",
    ) -> None:
        super().__init__()
        self.config = config
        self.prefix = prefix  # of its state keys
        self.blocks = nn.ModuleList(
            Block(config, mechanism=mechanism, generator=generator, carries_fine=i == 0)
            for i in range(config.n_layers)
        )
        self.norm = nn.LayerNorm(config.embed_dim)

    def _position(self, x: Tensor, positions: Tensor) -> Tensor:
        if self.config.pos_encoding == "none":
            return x
        pe = sinusoidal_encoding(positions, self.config.embed_dim, base=self.config.pos_base)
        return x + pe.unsqueeze(-2).to(x.dtype)  # the same code at every place of a view

    def forward(
        self, x: Tensor, extra: Tensor | None = None
    ) -> Tensor | tuple[Tensor, Tensor]:
        """(B, L, P, D) -> (B, L, P, D); with ``extra`` (the fine memory's tokens, read by the
        first block's attention) also what was read of it."""
        x = self._position(x, torch.arange(x.shape[1], device=x.device))
        read = None
        for i, block in enumerate(self.blocks):
            x, r = block(x, extra if i == 0 else None)
            read = r if i == 0 else read
        return self.norm(x) if extra is None else (self.norm(x), read)

    def init_state(self, batch: int, *, device: torch.device) -> State:
        state: State = {}
        for i, block in enumerate(self.blocks):
            state |= block.attn.init_state(batch, device=device, prefix=f"{self.prefix}layer{i}.")
        return state

    def step(
        self, x: Tensor, t: Tensor, state: State, *, extra: Tensor | None = None
    ) -> tuple[Tensor | tuple[Tensor, Tensor], State]:
        """x (B, P, D), t 0-d view index -> (B, P, D) (with ``extra``: and what was read of
        it, as in :meth:`forward`), new tower state."""
        x = self._position(x, t.expand(x.shape[0]))
        new: State = {}
        read = None
        for i, block in enumerate(self.blocks):
            x, r, entries = block.step(x, t, state, prefix=f"{self.prefix}layer{i}.",
                                       extra=extra if i == 0 else None)
            read = r if i == 0 else read
            new |= entries
        return (self.norm(x) if extra is None else (self.norm(x), read)), new


class LSTMTower(nn.Module):
    """LSTM over the views' tokens, one recurrence per place (shared weights); no positional
    encoding: the recurrence orders the views."""

    def __init__(self, config: ModelConfig, *, places: int = 1, prefix: str = "") -> None:
        super().__init__()
        self.h, self.c = f"{prefix}lstm.h", f"{prefix}lstm.c"  # state keys
        self.n_layers = config.n_layers
        self.dim = config.embed_dim
        self.places = places
        self.lstm = nn.LSTM(config.embed_dim, config.embed_dim, config.n_layers, batch_first=True)

    def forward(self, x: Tensor) -> Tensor:  # (B, L, P, D) -> (B, L, P, D)
        b, n, p, d = x.shape
        y = self.lstm(x.transpose(1, 2).reshape(b * p, n, d))[0]  # (B·P, L, D)
        return y.view(b, p, n, d).transpose(1, 2)

    def init_state(self, batch: int, *, device: torch.device) -> State:
        h = torch.zeros(self.n_layers, batch * self.places, self.dim, device=device)
        return {self.h: h, self.c: h.clone()}

    def step(self, x: Tensor, t: Tensor, state: State) -> tuple[Tensor, State]:
        b, p, d = x.shape
        y, (h, c) = self.lstm(x.reshape(b * p, 1, d), (state[self.h], state[self.c]))
        return y.view(b, p, d), {self.h: h, self.c: c}
