"""Causal linear attention with an explicit constant-size state (Performer: FAVOR+, ReLU).

Axis letters (as in :mod:`completion.model`): ``...`` any leading batch axes (batch, heads),
``L`` sequence (views), ``E`` query/key head size, ``F`` value head size, ``M`` random features.

The attention output for position i is (paper, Eq. 2)::

    x_i = φ(q_i) S_i / φ(q_i) z_i,   S_i = Σ_{j≤i} φ(k_j)ᵀ v_j (M, F),   z_i = Σ_{j≤i} φ(k_j) (M,)

computed either in parallel over a whole sequence (prefix sums, :func:`causal_linear_attention`)
or one position at a time from the carried state (S, z) (:func:`linear_attention_step`). Both
forms accumulate in float32 and give the same numbers.

Kernels
-------
``"softmax"`` (FAVOR+, Choromanski et al. 2021): q and k are scaled by E^-1/4 so that
φ(q)·φ(k) estimates exp(q·k / √E); φ(x)_i = M^-1/2 · exp(ω_iᵀx − ‖x‖²/2) with the rows ω_i of a
:func:`orthogonal_random_features` matrix (orthogonal blocks, chi-distributed row norms).

``"relu"``: deterministic φ(x) = ReLU(x) + ε with ε = :data:`RELU_KERNEL_EPS`, so the
normaliser φ(q)·z never vanishes.

Numerical stabilisation (no statistic crosses time)
---------------------------------------------------
A sequence-global shift of the exponent makes earlier outputs depend on later keys (the bug of
performer-pytorch issue #82). Here every shift is either a constant of the random features or a
quantity of one position only:

* keys: feature i is multiplied by the fixed constant exp(−‖ω_i‖²/2), which gives
  φ(k)_i = M^-1/2 · exp(−‖k − ω_i‖²/2) ≤ M^-1/2 — it can never overflow, whatever the data;
* queries: feature i is multiplied by the inverse constant exp(+‖ω_i‖²/2), so every product
  φ(q)_i φ(k)_i — and hence the kernel estimate — is exactly unchanged; then each query is shifted
  by its own maximum over the feature axis, which cancels between numerator and denominator.

The state (S, z) therefore needs no running maximum and no rescaling; appending positions never
changes earlier outputs. A key far from every ω_i (‖k − ω_i‖² > ~170 for all i) underflows to a
zero contribution instead of producing inf/NaN.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from completion.config import KERNELS, Kernel

RELU_KERNEL_EPS = 1e-3
"""Added to ReLU features so that the normaliser φ(q)·z is strictly positive."""

STATE_DTYPE = torch.float32
"""The carried state (S, z) and the prefix sums are always accumulated in this dtype."""


def _check_kernel(kernel: str) -> None:
    if kernel not in KERNELS:
        raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")


def orthogonal_random_features(
    n_features: int, dim: int, *, generator: torch.Generator | None = None
) -> Tensor:
    """Draw FAVOR+ projection rows: (n_features, dim) float32 (M, E).

    Rows come in blocks of ``dim`` mutually orthogonal directions (QR of a Gaussian matrix, signs
    fixed by diag(R) so that each block is Haar-distributed); each row is then rescaled to the
    norm of an independent standard Gaussian vector of size ``dim`` (chi-distributed), so each
    row is marginally N(0, I) while rows within a block stay orthogonal. Drawn in float64 on the
    CPU, hence identical on every device for a given generator state.
    """
    if n_features < 1 or dim < 1:
        raise ValueError(f"n_features and dim must be >= 1, got {n_features} and {dim}")
    n_blocks = math.ceil(n_features / dim)
    blocks = []
    for _ in range(n_blocks):
        gaussian = torch.randn(dim, dim, generator=generator, dtype=torch.float64)
        q, r = torch.linalg.qr(gaussian)
        q = q * torch.sign(torch.diagonal(r)).where(torch.diagonal(r) != 0, 1.0)
        blocks.append(q.T)  # rows orthonormal
    directions = torch.cat(blocks, dim=0)[:n_features]  # (M, E)
    norms = torch.randn(n_features, dim, generator=generator, dtype=torch.float64).norm(dim=1)
    return (directions * norms[:, None]).to(torch.float32)


def softmax_kernel_features(x: Tensor, omega: Tensor, *, is_query: bool) -> Tensor:
    """FAVOR+ positive random features of ``x``: (..., E) -> (..., M) float32.

    ``x`` is the raw query or key; it is scaled by E^-1/4 here. ``omega`` is (M, E). The
    stabilising shifts (module docstring) leave φ(q)·φ(k) an unbiased estimate of exp(q·k/√E) up
    to a positive factor of the query alone, which cancels in attention.
    """
    dim = x.shape[-1]
    if omega.ndim != 2 or omega.shape[1] != dim:
        raise ValueError(f"omega must be (M, {dim}), got {tuple(omega.shape)}")
    xs = x.to(torch.float32) * dim**-0.25
    omega = omega.to(device=xs.device, dtype=torch.float32)
    proj = xs @ omega.T  # (..., M)
    x_sq = 0.5 * (xs * xs).sum(dim=-1, keepdim=True)  # (..., 1)
    omega_sq = 0.5 * (omega * omega).sum(dim=-1)  # (M,)
    log_norm = -0.5 * math.log(omega.shape[0])
    if is_query:
        logits = proj - x_sq + omega_sq
        logits = logits - logits.amax(dim=-1, keepdim=True).detach()
    else:
        logits = proj - x_sq - omega_sq  # = -‖x - ω_i‖²/2 <= 0
    return torch.exp(logits + log_norm)


def relu_kernel_features(x: Tensor) -> Tensor:
    """Deterministic ReLU features: (..., E) -> (..., E) float32, φ(x) = ReLU(x) + ε."""
    return torch.relu(x.to(torch.float32)) + RELU_KERNEL_EPS


def _safe_divide(num: Tensor, den: Tensor) -> Tensor:
    """num (..., F) / den (...,), with den clamped to the smallest normal float32."""
    return num / den.clamp_min(torch.finfo(den.dtype).tiny).unsqueeze(-1)


def causal_linear_attention(phi_q: Tensor, phi_k: Tensor, v: Tensor) -> Tensor:
    """Parallel causal linear attention by prefix sums over L.

    phi_q, phi_k: (..., L, M) features; v: (..., L, F). Returns (..., L, F) float32.
    Memory is O(L·M·F) per leading index (the prefix sums of φ(k)ᵀv are materialised).
    """
    if phi_q.shape != phi_k.shape or phi_k.shape[:-1] != v.shape[:-1]:
        raise ValueError(
            f"expected phi_q, phi_k (..., L, M) and v (..., L, F) with matching axes, got "
            f"{tuple(phi_q.shape)}, {tuple(phi_k.shape)}, {tuple(v.shape)}"
        )
    return block_causal_linear_attention(
        phi_q.unsqueeze(-2), phi_k.unsqueeze(-2), v.unsqueeze(-2)
    ).squeeze(-2)


def block_causal_linear_attention(phi_q: Tensor, phi_k: Tensor, v: Tensor) -> Tensor:
    """Causal over views, full within a view: position (i, p) attends to every (j, p') with
    j ≤ i. phi_q, phi_k: (..., L, P, M); v: (..., L, P, F) -> (..., L, P, F) float32.

    P = 1 is :func:`causal_linear_attention`, with the same operations (so the same bits).
    """
    if phi_q.shape != phi_k.shape or phi_k.shape[:-1] != v.shape[:-1] or phi_q.ndim < 3:
        raise ValueError(
            f"expected phi_q, phi_k (..., L, P, M) and v (..., L, P, F) with matching axes, got "
            f"{tuple(phi_q.shape)}, {tuple(phi_k.shape)}, {tuple(v.shape)}"
        )
    phi_q = phi_q.to(STATE_DTYPE)
    phi_k = phi_k.to(STATE_DTYPE)
    v = v.to(STATE_DTYPE)
    kv = (phi_k.unsqueeze(-1) * v.unsqueeze(-2)).sum(dim=-3)  # (..., L, M, F)
    s = torch.cumsum(kv, dim=-3)  # (..., L, M, F)
    z = torch.cumsum(phi_k.sum(dim=-2), dim=-2)  # (..., L, M)
    num = (phi_q.unsqueeze(-1) * s.unsqueeze(-3)).sum(dim=-2)  # (..., L, P, F)
    den = (phi_q * z.unsqueeze(-2)).sum(dim=-1)  # (..., L, P)
    return _safe_divide(num, den)


def init_linear_attention_state(
    batch_shape: tuple[int, ...],
    n_features: int,
    dim_v: int,
    *,
    device: torch.device | str | None = None,
) -> tuple[Tensor, Tensor]:
    """Empty memory: S (*batch_shape, M, F) and z (*batch_shape, M), zeros in float32."""
    s = torch.zeros(*batch_shape, n_features, dim_v, dtype=STATE_DTYPE, device=device)
    z = torch.zeros(*batch_shape, n_features, dtype=STATE_DTYPE, device=device)
    return s, z


def linear_attention_step(
    phi_q: Tensor, phi_k: Tensor, v: Tensor, s: Tensor, z: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """One recurrent step: add (φ(k), v) to the memory, then read it with φ(q).

    phi_q, phi_k: (..., M); v: (..., F); s: (..., M, F); z: (..., M).
    Returns (out (..., F) float32, new s, new z); the inputs are not modified.
    """
    if (
        phi_q.shape != phi_k.shape
        or s.shape != (*phi_k.shape, v.shape[-1])
        or z.shape != phi_k.shape
    ):
        raise ValueError(
            f"expected phi_q, phi_k (..., M), v (..., F), s (..., M, F), z (..., M), got "
            f"{tuple(phi_q.shape)}, {tuple(phi_k.shape)}, {tuple(v.shape)}, {tuple(s.shape)}, "
            f"{tuple(z.shape)}"
        )
    out, s, z = block_linear_attention_step(
        phi_q.unsqueeze(-2), phi_k.unsqueeze(-2), v.unsqueeze(-2), s, z
    )
    return out.squeeze(-2), s, z


def block_linear_attention_step(
    phi_q: Tensor, phi_k: Tensor, v: Tensor, s: Tensor, z: Tensor
) -> tuple[Tensor, Tensor, Tensor]:
    """One view of :func:`block_causal_linear_attention`: add its P places to the memory, then
    read it at each. phi_q, phi_k: (..., P, M); v: (..., P, F); s: (..., M, F); z: (..., M).
    Returns (out (..., P, F) float32, new s, new z); the memory's size does not depend on P's
    history, only on M and F.
    """
    if (
        phi_q.shape != phi_k.shape
        or phi_k.shape[:-1] != v.shape[:-1]
        or s.shape != (*phi_k.shape[:-2], phi_k.shape[-1], v.shape[-1])
        or z.shape != (*phi_k.shape[:-2], phi_k.shape[-1])
    ):
        raise ValueError(
            f"expected phi_q, phi_k (..., P, M), v (..., P, F), s (..., M, F), z (..., M), got "
            f"{tuple(phi_q.shape)}, {tuple(phi_k.shape)}, {tuple(v.shape)}, {tuple(s.shape)}, "
            f"{tuple(z.shape)}"
        )
    phi_q = phi_q.to(STATE_DTYPE)
    phi_k = phi_k.to(STATE_DTYPE)
    s = s + (phi_k.unsqueeze(-1) * v.to(STATE_DTYPE).unsqueeze(-2)).sum(dim=-3)
    z = z + phi_k.sum(dim=-2)
    num = (phi_q.unsqueeze(-1) * s.unsqueeze(-3)).sum(dim=-2)  # (..., P, F)
    den = (phi_q * z.unsqueeze(-2)).sum(dim=-1)  # (..., P)
    return _safe_divide(num, den), s, z


def causal_softmax_attention(q: Tensor, k: Tensor, v: Tensor) -> Tensor:
    """Exact causal softmax attention, the reference FAVOR+ estimates.

    q, k: (..., L, E); v: (..., L, F). Returns (..., L, F) with weights softmax(q·k/√E) over j ≤ i.
    """
    q, k, v = (x.unsqueeze(-2) for x in (q, k, v))  # one place per view
    return block_causal_softmax_attention(q, k, v).squeeze(-2)


def block_causal_softmax_attention(q: Tensor, k: Tensor, v: Tensor) -> Tensor:
    """Exact softmax attention, causal over views and full within a view.

    q, k: (..., L, P, E); v: (..., L, P, F) -> (..., L, P, F): position (i, p) weighs every
    (j, p') with j ≤ i by softmax(q·k/√E).
    """
    n, places = q.shape[-3], q.shape[-2]
    view = torch.arange(n, device=q.device).repeat_interleave(places)  # (L·P,)
    q, k, v = (x.flatten(-3, -2) for x in (q, k, v))  # (..., L·P, ·)
    scores = (q @ k.transpose(-1, -2)) * q.shape[-1] ** -0.5  # (..., L·P, L·P)
    future = view.unsqueeze(1) < view.unsqueeze(0)
    scores = scores.masked_fill(future, float("-inf"))
    out = torch.softmax(scores, dim=-1) @ v
    return out.unflatten(-2, (n, places))


class FeatureMap(nn.Module):
    """φ for one attention layer; the FAVOR+ projection is a registered (saved) buffer.

    ``forward(x, is_query=...)``: (..., E) -> (..., M) float32. For ``kernel="relu"`` M = E and
    there is no buffer content to speak of (an empty one keeps state dicts uniform).
    """

    omega: Tensor

    def __init__(
        self,
        dim: int,
        *,
        kernel: Kernel = "softmax",
        n_features: int = 128,
        generator: torch.Generator | None = None,
    ) -> None:
        super().__init__()
        _check_kernel(kernel)
        if dim < 1 or n_features < 1:
            raise ValueError(f"dim and n_features must be >= 1, got {dim} and {n_features}")
        self.dim = dim
        self.kernel: Kernel = kernel
        if kernel == "softmax":
            self.n_features = n_features
            omega = orthogonal_random_features(n_features, dim, generator=generator)
        else:
            self.n_features = dim
            omega = torch.empty(0, dim)
        self.register_buffer("omega", omega, persistent=True)

    def redraw(self, *, generator: torch.Generator) -> None:
        """Draw a new FAVOR+ projection in place (training only; no-op for the ReLU kernel)."""
        if self.kernel == "softmax":
            fresh = orthogonal_random_features(self.n_features, self.dim, generator=generator)
            self.omega.copy_(fresh.to(self.omega.device))

    def forward(self, x: Tensor, *, is_query: bool) -> Tensor:
        if x.shape[-1] != self.dim:
            raise ValueError(f"expected last axis {self.dim}, got {tuple(x.shape)}")
        if self.kernel == "softmax":
            return softmax_kernel_features(x, self.omega, is_query=is_query)
        return relu_kernel_features(x)

    def extra_repr(self) -> str:
        return f"dim={self.dim}, kernel={self.kernel!r}, n_features={self.n_features}"
