"""The shift memory: a constant-size memory that carries a shape along the image's x axis by any
fraction of a cell (``ModelConfig.shift_heads``).

The place path moves features between the 5³ places of the bottleneck (8 voxels a side), and a
transport rounded to whole places is worth nothing on slide behind (model card, the
``completion.headroom --shift-quantum`` bounds): the slider moves 15–26 voxels and lands up to
half a place off. Here each view writes its finest context level ((G/2)³ cells of 2 voxels) into
one memory per row (j, k) along i (camera x, the image's horizontal) as a Fourier series along i,
in the frame of where the view stands: a distribution over its cells along i (a softmax over the
cells it sees, from their features and coordinates, so that it can pick out the object behind). The
current view reads the series back in the frame of where it stands. What view s wrote at cell i
reaches view t at i + x_t − x_s, x_s and x_t drawn from the two distributions: for point-like
ones a phase per frequency, so a move by any fraction of a cell. The distributions blend every
move at first (uniform), so a far move that pays gets a gradient, where a single mean position
would be stuck (a shape moved a little does not reach a target 10 cells away). Per head: what to
write (values times a sigmoid gate per cell), where the view stands to write and to read, and a
gain per frequency (a Hann taper at the start). With ``shift_decoded`` a view also writes the
decoder's features at that level (the shape it completes, where the context encoder has only
the surface it saw), through a second value layer that starts at zero. The read is divided by
1 + the gate mass written so far in its row, and added to the decoder's (G/2)³ skip by a 1×1×1
conv that starts at zero, so a checkpoint without this memory warm-starts it exactly.

Memory per head: (Cv, M, n, n) complex numbers (two real tensors) and (n, n) written mass, n =
G/2, M frequencies of period 2n (so a shape moved by up to n cells does not wrap onto itself),
whatever the number of views. Shapes: N frames, B sequences, L views, H heads, Cv channels.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from completion.conv import Conv3d

State = dict[str, Tensor]
PREFIX = "shift."


# E[exp(i ω_m x)] over where a view stands x, real and imaginary parts, each (N, H, M)
Frame = tuple[Tensor, Tensor]


def frame_at(p: Tensor, omega: Tensor) -> Frame:
    """The frame of a view that stands exactly at p (N, H) along i."""
    angle = p[..., None] * omega
    return torch.cos(angle), torch.sin(angle)


def frame_of(weights: Tensor, omega: Tensor) -> Frame:
    """The frame of a view that stands at cell i with probability weights[..., i] (N, H, n): the
    characteristic function of that distribution. A move between two such frames is the blend
    of every move between their cells, so each cell's weight gets a gradient from its own move
    however far it is (a mean position would get one only from moves within the shape's reach)."""
    cos, sin = _tables(omega, weights.shape[-1])
    return weights @ cos.T, weights @ sin.T


def fourier_write(content: Tensor, frame: Frame, omega: Tensor) -> tuple[Tensor, Tensor]:
    """content (N, H, C, n, n, n) along i, j, k; the writer's frame; omega (M,) the frequencies
    -> the series of content(i) · exp(−i ω_m (i − x)) over the writer's x, real and imaginary
    parts, each (N, H, C, M, n, n)."""
    cos, sin = _tables(omega, content.shape[3])
    a = torch.einsum("nhcijk,mi->nhcmjk", content, cos)  # Σ content · cos(ω i)
    b = -torch.einsum("nhcijk,mi->nhcmjk", content, sin)  # Σ content · −sin(ω i)
    return _turn(a, b, frame)


def fourier_read(re: Tensor, im: Tensor, frame: Frame, gain: Tensor, omega: Tensor,
                 n: int) -> Tensor:
    """The series (N, H, C, M, n, n) read in the reader's frame at the n cells along i:
    Σ_m gain_m · Re(S_m · exp(i ω_m (i − x))) over the reader's x -> (N, H, C, n, n, n).
    gain (H, M)."""
    cos, sin = _tables(omega, n)
    re, im = _turn(re, im, (frame[0], -frame[1]))
    g = gain[None, :, None, :, None, None]
    return (torch.einsum("nhcmjk,mi->nhcijk", re * g, cos)
            - torch.einsum("nhcmjk,mi->nhcijk", im * g, sin))


def _tables(omega: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """cos and sin of ω_m · i, (M, n)."""
    angle = omega[:, None] * torch.arange(n, device=omega.device, dtype=omega.dtype)
    return torch.cos(angle), torch.sin(angle)


def _turn(re: Tensor, im: Tensor, frame: Frame) -> tuple[Tensor, Tensor]:
    """(re + i·im) · frame, the frame (N, H, M) broadcast over channels and rows."""
    c, s = (f[:, :, None, :, None, None] for f in frame)
    return re * c - im * s, re * s + im * c


class ShiftMemory(nn.Module):
    """The memory of the module docstring, over the context encoder's finest level."""

    def __init__(self, config) -> None:  # config: completion.model.ModelConfig
        super().__init__()
        c0 = config.channels[0]
        self.n = n = config.grid_size // 2
        self.heads, self.channels = config.shift_heads, config.shift_channels
        self.freqs = m = config.shift_freqs or n
        self.value = Conv3d(c0, self.heads * self.channels, 1)
        # ``shift_decoded``: what the decoder makes of the view is written too, from zero
        self.value_decoded: Conv3d | None = None
        if config.shift_decoded:
            self.value_decoded = Conv3d(c0, self.heads * self.channels, 1, bias=False)
            nn.init.zeros_(self.value_decoded.weight)
        # what to write and where a view stands depend on where a cell is, too (the object behind
        # is further away): a per-cell layer over the features and the cell's coordinates
        hidden = 2 * c0
        self.cell = nn.Sequential(Conv3d(c0 + 3, hidden, 1), nn.ReLU())
        self.gate = Conv3d(hidden, self.heads, 1)
        self.where = Conv3d(hidden, 2 * self.heads, 1)  # write and read reference logits
        nn.init.zeros_(self.where.weight)  # uniform at first: every view the same reference
        nn.init.zeros_(self.where.bias)
        self.out = Conv3d(self.heads * self.channels, c0, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)
        k = torch.arange(m, dtype=torch.float64)
        taper = 0.5 * (1 + torch.cos(math.pi * k / m))  # Hann: little ringing
        gain = torch.where(k == 0, 1.0, 2.0) / (2 * n) * taper
        self.gain = nn.Parameter(gain.float().repeat(self.heads, 1))  # (H, M)
        # ω_m = π m / n: period 2n cells, so a shape moved by up to n cells does not wrap
        self.register_buffer("omega", (math.pi * k / n).float(), persistent=False)
        axis = torch.linspace(-1, 1, n)
        coords = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"))  # (3, n, n, n)
        self.register_buffer("coords", coords, persistent=False)
        # a list while training with --where-weight: each forward appends where the frames
        # stand, (N, 2H, n) probabilities along i (completion.train.where_loss)
        self.record: list[Tensor] | None = None

    def _view(self, level: Tensor, frames: Tensor,
              decoded: Tensor | None) -> tuple[Tensor, Tensor, Tensor, Frame]:
        """One frame's part: level (N, C0, n, n, n), the occupancy it came from (N, G, G, G)
        and (``shift_decoded``) the decoder's features at that level (N, C0, n, n, n) -> series
        re, im (N, H, Cv, M, n, n), gate mass per row (N, H, n, n), and the frame it reads in."""
        x = level.float()
        heads, n = self.heads, self.n
        cells = self._cells(x)
        gate = torch.sigmoid(self.gate(cells))  # (N, H, n, n, n)
        value = self.value(x)
        if (decoded is None) != (self.value_decoded is None):
            raise ValueError("the decoder's features are needed exactly when shift_decoded is set")
        if self.value_decoded is not None:
            value = value + self.value_decoded(decoded.float())
        value = value.view(x.shape[0], heads, self.channels, n, n, n)
        write, read = self._frames(cells, frames)
        re, im = fourier_write(value * gate[:, :, None], write, self.omega)
        return re, im, gate.sum(dim=2), read

    def _frames(self, cells: Tensor, frames: Tensor) -> tuple[Frame, Frame]:
        """Where each frame stands to write and to read: the frames of its two distributions
        (``completion.headroom.standing_at`` replaces this to stand exactly where it says)."""
        where = self._where(cells, frames)
        if self.record is not None:
            self.record.append(where)
        heads = self.heads
        return frame_of(where[:, :heads], self.omega), frame_of(where[:, heads:], self.omega)

    def _cells(self, x: Tensor) -> Tensor:
        coords = self.coords.expand(x.shape[0], -1, -1, -1, -1)
        return self.cell(torch.cat((x, coords), dim=1))

    def _where(self, cells: Tensor, frames: Tensor) -> Tensor:
        """(N, 2H, n): where the view stands along i to write (first H) and to read, a softmax
        over the cells it sees (any voxel of the cell occupied; every cell for an empty view),
        summed over j and k. Uniform over what it sees at first."""
        seen = nn.functional.max_pool3d(frames[:, None].float(), 2).flatten(1) > 0  # (N, n³)
        unseen = (~seen & seen.any(-1, keepdim=True))[:, None]
        logits = self.where(cells).flatten(2).masked_fill(unseen, -1e4)  # (N, 2H, n³)
        where = torch.softmax(logits, dim=-1)  # i slowest
        return where.view(*where.shape[:2], self.n, -1).sum(-1)

    def references(self, level: Tensor, frames: Tensor) -> tuple[Tensor, Tensor]:
        """Where each frame stands along i on average, in cells of its level (N, C0, n, n, n)
        (frames: the occupancy it came from): the write and the read reference, each (N, H)."""
        where = self._where(self._cells(level.float()), frames)
        p = where @ torch.arange(self.n, device=where.device, dtype=where.dtype)
        return p[:, : self.heads], p[:, self.heads :]

    def _read(self, re: Tensor, im: Tensor, mass: Tensor, frame: Frame) -> Tensor:
        y = fourier_read(re, im, frame, self.gain, self.omega, self.n)
        y = y / (1 + mass[:, :, None, None])  # (N, H, Cv, n, n, n)
        return self.out(y.flatten(1, 2))

    def forward(self, level: Tensor, frames: Tensor, batch: tuple[int, int],
                decoded: Tensor | None = None) -> Tensor:
        """Parallel: the finest context level of every frame (B·L, C0, n, n, n), the frames
        (B·L, G, G, G) and, with ``shift_decoded``, the decoder's features at that level (B·L,
        C0, n, n, n), in (B, L) order -> what each view reads, (B·L, C0, n, n, n), causal over
        views."""
        with torch.autocast(device_type=level.device.type, enabled=False):
            re, im, mass, frame = self._view(level, frames, decoded)
            b, views = batch
            re, im, mass = (t.view(b, views, *t.shape[1:]).cumsum(1).flatten(0, 1)
                            for t in (re, im, mass))
            return self._read(re, im, mass, frame)

    def init_state(self, batch: int, *, device: torch.device) -> State:
        n, shape = self.n, (batch, self.heads, self.channels, self.freqs, self.n, self.n)
        return {f"{PREFIX}re": torch.zeros(shape, device=device),
                f"{PREFIX}im": torch.zeros(shape, device=device),
                f"{PREFIX}mass": torch.zeros(batch, self.heads, n, n, device=device)}

    def step(self, level: Tensor, frames: Tensor, state: State,
             decoded: Tensor | None = None) -> tuple[Tensor, State]:
        """Streaming: one view's finest context level (B, C0, n, n, n), its frame (B, G, G, G)
        and, with ``shift_decoded``, the decoder's features there -> what it reads, and the new
        state entries."""
        with torch.autocast(device_type=level.device.type, enabled=False):
            re, im, mass, frame = self._view(level, frames, decoded)
            re, im = state[f"{PREFIX}re"] + re, state[f"{PREFIX}im"] + im
            mass = state[f"{PREFIX}mass"] + mass
            new = {f"{PREFIX}re": re, f"{PREFIX}im": im, f"{PREFIX}mass": mass}
            return self._read(re, im, mass, frame), new
