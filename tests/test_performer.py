"""FAVOR+ / ReLU causal linear attention: estimator quality, parallel == recurrent, causality."""

from __future__ import annotations

import math

import pytest
import torch

from completion.performer import (
    RELU_KERNEL_EPS,
    FeatureMap,
    causal_linear_attention,
    causal_softmax_attention,
    init_linear_attention_state,
    linear_attention_step,
    orthogonal_random_features,
    relu_kernel_features,
    softmax_kernel_features,
)

torch.set_num_threads(1)


def _qkv(*shape: int, scale: float = 0.5, seed: int = 0) -> tuple[torch.Tensor, ...]:
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(*shape, generator=g) * scale
    k = torch.randn(*shape, generator=g) * scale
    v = torch.randn(*shape, generator=g)
    return q, k, v


def _recurrent(fm: FeatureMap, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Run linear_attention_step over axis -2 of (..., L, E) inputs."""
    s, z = init_linear_attention_state(q.shape[:-2], fm.n_features, v.shape[-1])
    outs = []
    for t in range(q.shape[-2]):
        out, s, z = linear_attention_step(
            fm(q[..., t, :], is_query=True), fm(k[..., t, :], is_query=False), v[..., t, :], s, z
        )
        outs.append(out)
    return torch.stack(outs, dim=-2)


def _parallel(fm: FeatureMap, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return causal_linear_attention(fm(q, is_query=True), fm(k, is_query=False), v)


def test_orthogonal_random_features_blocks_are_orthogonal_with_gaussian_norms() -> None:
    dim, m = 16, 40  # two full blocks and a partial one
    omega = orthogonal_random_features(m, dim, generator=torch.Generator().manual_seed(0))
    assert omega.shape == (m, dim) and omega.dtype == torch.float32
    for start in (0, 16, 32):
        block = omega[start : start + dim].double()
        unit = block / block.norm(dim=1, keepdim=True)
        gram = unit @ unit.T
        torch.testing.assert_close(
            gram, torch.eye(len(block), dtype=torch.float64), atol=1e-5, rtol=0
        )
    # norms are chi(dim)-distributed, not all equal: mean ≈ sqrt(dim - 1/2) and non-zero spread
    many = orthogonal_random_features(4096, dim, generator=torch.Generator().manual_seed(1))
    norms = many.norm(dim=1)
    assert abs(norms.mean().item() - math.sqrt(dim - 0.5)) < 0.1
    assert 0.5 < norms.std().item() < 0.9  # chi_16 std ≈ 0.70


def test_orthogonal_random_features_are_deterministic_per_generator() -> None:
    a = orthogonal_random_features(32, 8, generator=torch.Generator().manual_seed(3))
    b = orthogonal_random_features(32, 8, generator=torch.Generator().manual_seed(3))
    c = orthogonal_random_features(32, 8, generator=torch.Generator().manual_seed(4))
    assert torch.equal(a, b)
    assert not torch.equal(a, c)


def test_stabilised_features_give_the_textbook_kernel_estimate() -> None:
    """φ(q)·φ(k) after the fixed key shift and per-query shift equals the plain FAVOR+ formula
    φ(x) = m^-1/2 exp(ωᵀx − ‖x‖²/2), x scaled by d^-1/4, up to a positive factor of q only."""
    dim, m = 8, 64
    q, k, _ = _qkv(5, dim, scale=1.0)
    omega = orthogonal_random_features(m, dim, generator=torch.Generator().manual_seed(0))

    def plain(x: torch.Tensor) -> torch.Tensor:
        xs = x.double() * dim**-0.25
        return torch.exp(xs @ omega.double().T - 0.5 * (xs * xs).sum(-1, keepdim=True)) / m**0.5

    expected = plain(q) @ plain(k).T  # (5 queries, 5 keys)
    got = (
        softmax_kernel_features(q, omega, is_query=True)
        @ softmax_kernel_features(k, omega, is_query=False).T
    ).double()
    ratio = got / expected  # one positive constant per query (row)
    torch.testing.assert_close(ratio, ratio[:, :1].expand_as(ratio), rtol=1e-5, atol=0)
    assert (ratio > 0).all()


def test_key_features_are_bounded_whatever_the_input() -> None:
    omega = orthogonal_random_features(32, 8, generator=torch.Generator().manual_seed(0))
    k = torch.randn(100, 8) * 30.0
    phi_k = softmax_kernel_features(k, omega, is_query=False)
    assert torch.isfinite(phi_k).all()
    assert (phi_k <= 32**-0.5 + 1e-7).all()
    phi_q = softmax_kernel_features(k, omega, is_query=True)
    assert torch.isfinite(phi_q).all()
    torch.testing.assert_close(phi_q.amax(-1), torch.full((100,), 32**-0.5))


def _favor_error(n_features: int, *, seeds: range = range(3)) -> float:
    q, k, v = _qkv(2, 2, 16, 16, scale=0.5)  # (B, H, L, E)
    exact = causal_softmax_attention(q, k, v)
    errors = []
    for seed in seeds:
        fm = FeatureMap(16, n_features=n_features, generator=torch.Generator().manual_seed(seed))
        approx = _parallel(fm, q, k, v)
        errors.append(((approx - exact).norm() / exact.norm()).item())
    return sum(errors) / len(errors)


def test_favor_approximates_exact_softmax_attention_and_improves_with_features() -> None:
    errors = {m: _favor_error(m) for m in (64, 512, 4096)}
    assert errors[4096] < 0.05, errors
    assert errors[64] > errors[512] > errors[4096], errors


@pytest.mark.parametrize("kernel", ["softmax", "relu"])
def test_parallel_equals_recurrent(kernel: str) -> None:
    q, k, v = _qkv(3, 2, 12, 8, scale=1.0)  # (B, H, L, E)
    fm = FeatureMap(8, kernel=kernel, n_features=32, generator=torch.Generator().manual_seed(0))
    parallel = _parallel(fm, q, k, v)
    recurrent = _recurrent(fm, q, k, v)
    assert parallel.dtype == recurrent.dtype == torch.float32
    torch.testing.assert_close(parallel, recurrent, atol=1e-6, rtol=1e-5)


def test_relu_attention_matches_quadratic_reference() -> None:
    q, k, v = _qkv(7, 4, scale=1.0)
    fm = FeatureMap(4, kernel="relu")
    weights = (torch.relu(q) + RELU_KERNEL_EPS) @ (torch.relu(k) + RELU_KERNEL_EPS).T  # (L, L)
    weights = weights.tril()
    expected = (weights @ v) / weights.sum(-1, keepdim=True)
    torch.testing.assert_close(_parallel(fm, q, k, v), expected, atol=1e-6, rtol=1e-5)
    assert torch.equal(relu_kernel_features(torch.tensor([-1.0, 2.0])), torch.tensor([1e-3, 2.001]))


@pytest.mark.parametrize("kernel", ["softmax", "relu"])
def test_appending_positions_never_changes_earlier_outputs(kernel: str) -> None:
    """The performer-pytorch #82 failure: later keys with a huge norm must not touch the past."""
    q, k, v = _qkv(2, 10, 8, scale=1.0)
    fm = FeatureMap(8, kernel=kernel, n_features=32, generator=torch.Generator().manual_seed(0))
    short = _parallel(fm, q[:, :6], k[:, :6], v[:, :6])
    k_loud = k.clone()
    k_loud[:, 6:] *= 40.0  # appended keys far outside the range of the earlier ones
    long = _parallel(fm, q, k_loud, v)
    assert torch.isfinite(long).all()
    torch.testing.assert_close(long[:, :6], short, atol=0, rtol=0)


def test_huge_queries_and_keys_stay_finite_and_differentiable() -> None:
    q, k, v = _qkv(1, 2, 6, 8, scale=50.0)
    q.requires_grad_(True)
    k.requires_grad_(True)
    fm = FeatureMap(8, n_features=16, generator=torch.Generator().manual_seed(0))
    out = _parallel(fm, q, k, v)
    out.sum().backward()
    assert torch.isfinite(out).all()
    assert torch.isfinite(q.grad).all() and torch.isfinite(k.grad).all()


def test_step_does_not_modify_its_inputs_and_keeps_fp32_state() -> None:
    s, z = init_linear_attention_state((2,), 4, 3)
    phi = torch.rand(2, 4)
    out, s1, z1 = linear_attention_step(phi, phi, torch.ones(2, 3, dtype=torch.float64), s, z)
    assert s.abs().sum() == 0 and z.abs().sum() == 0
    assert s1.dtype == z1.dtype == out.dtype == torch.float32
    torch.testing.assert_close(out, torch.ones(2, 3))  # one value seen: attention returns it


def test_feature_map_buffer_is_saved_and_redraw_is_seeded() -> None:
    fm = FeatureMap(8, n_features=16, generator=torch.Generator().manual_seed(0))
    assert "omega" in fm.state_dict()
    before = fm.omega.clone()
    fm.redraw(generator=torch.Generator().manual_seed(5))
    after = fm.omega.clone()
    assert not torch.equal(before, after)
    fm.redraw(generator=torch.Generator().manual_seed(5))
    assert torch.equal(fm.omega, after)
    relu = FeatureMap(8, kernel="relu")
    relu.redraw(generator=torch.Generator().manual_seed(5))  # no-op
    assert relu.n_features == 8


def test_bad_arguments_raise_value_error() -> None:
    with pytest.raises(ValueError, match="kernel must be one of"):
        FeatureMap(8, kernel="cosine")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n_features"):
        orthogonal_random_features(0, 8)
    fm = FeatureMap(8, n_features=16)
    with pytest.raises(ValueError, match="last axis 8"):
        fm(torch.zeros(3, 5), is_query=True)
    with pytest.raises(ValueError, match="matching axes"):
        causal_linear_attention(torch.zeros(2, 4), torch.zeros(3, 4), torch.zeros(2, 5))


def test_block_attention_matches_its_definition_and_its_steps() -> None:
    """Several tokens per view: (i, p) reads every (j, p') with j ≤ i; the parallel form equals a
    direct sum and the one-view steps, and exact attention never reads a later view."""
    from completion.performer import (
        block_causal_linear_attention,
        block_causal_softmax_attention,
        block_linear_attention_step,
    )

    tokens, n, m, f = 3, 4, 5, 2
    g = torch.Generator().manual_seed(0)
    phi_q = torch.rand(2, n, tokens, m, generator=g) + 0.1
    phi_k = torch.rand(2, n, tokens, m, generator=g) + 0.1
    v = torch.randn(2, n, tokens, f, generator=g)
    expected = torch.zeros(2, n, tokens, f)
    for i in range(n):
        w = torch.einsum("bpm,bjqm->bpjq", phi_q[:, i], phi_k[:, : i + 1])  # (B, P, j, P')
        expected[:, i] = torch.einsum("bpjq,bjqf->bpf", w, v[:, : i + 1]) / w.sum((2, 3))[
            ..., None
        ]
    got = block_causal_linear_attention(phi_q, phi_k, v)
    torch.testing.assert_close(got, expected, atol=1e-5, rtol=1e-5)
    s, z = torch.zeros(2, m, f), torch.zeros(2, m)
    for i in range(n):
        out, s, z = block_linear_attention_step(phi_q[:, i], phi_k[:, i], v[:, i], s, z)
        torch.testing.assert_close(out, expected[:, i], atol=1e-5, rtol=1e-5)
    q, k, vv = torch.randn(3, 1, n, tokens, 4, generator=g)
    out = block_causal_softmax_attention(q, k, vv)
    changed = vv.clone()
    changed[0, 2] += 1.0  # view 2
    again = block_causal_softmax_attention(q, k, changed)
    assert torch.equal(out[0, :2], again[0, :2])  # earlier views: untouched
    assert not torch.equal(out[0, 3], again[0, 3])  # a later view reads it
