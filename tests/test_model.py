"""Completion models: streaming == parallel, causality, constant memory, serialisation, training."""

from __future__ import annotations

import io
from pathlib import Path

import pytest
import torch
from torch.nn import functional as F

from completion import model as model_module
from completion.config import DEFAULT_CONFIGS, MODEL_KINDS, ModelConfig, default_config
from completion.model import (
    CompletionModel,
    build_model,
    load_checkpoint,
    load_model,
    read_checkpoint,
    save_checkpoint,
    state_from_bytes,
    state_nbytes,
    state_to_bytes,
)
from completion.towers import AttentionTower, sinusoidal_encoding

torch.set_num_threads(1)

G = 40
ATOL = 1e-5

# (kind, kernel, rotary values in degrees per view): every model, MVP with both kernels, and
# the attention models with rotary values (as shipped)
VARIANTS = [
    ("single_view", "softmax", 0),
    ("mvp", "softmax", 0),
    ("mvp", "relu", 0),
    ("mvt", "softmax", 0),
    ("lstm", "softmax", 0),
    ("mvp", "softmax", 30),
    ("mvt", "softmax", 30),
]
IDS = [
    (f"{kind}-{kernel}" if kind == "mvp" else kind) + (f"-rot{rot}" if rot else "")
    for kind, kernel, rot in VARIANTS
]


def tiny_config(kind: str = "mvp", kernel: str = "softmax", **overrides: object) -> ModelConfig:
    values: dict[str, object] = {
        "kind": kind,
        "kernel": kernel,
        "channels": (2, 4, 8),
        "top_channels": 2,
        "token_channels": 2,
        "embed_dim": 16,
        "n_heads": 2,
        "n_layers": 2,
        "n_features": 16,
        "seed": 0,
    }
    values.update(overrides)
    return ModelConfig(**values)  # type: ignore[arg-type]


def scrambled(config: ModelConfig, *, seed: int = 0) -> CompletionModel:
    """A model with He-scaled random weights and random biases, so that logits are O(1–10) and
    every path (attention, memory, positional encoding) visibly matters; fresh inits decode ~0."""
    model = build_model(config).eval()
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for name, p in model.named_parameters():
            if p.ndim > 1:
                fan_in = p[0].numel()
                if ".ups." in name or "decoder.top." in name:
                    fan_in = p.shape[0]  # ConvTranspose, kernel 2 stride 2: one input voxel
                p.copy_(torch.randn(p.shape, generator=g) * (2.2 / fan_in) ** 0.5)
            elif "norm" not in name:
                p.copy_(torch.randn(p.shape, generator=g) * 0.1)
    return model


def random_views(batch: int, views: int, *, seed: int = 0, density: float = 0.05) -> torch.Tensor:
    """(B, L, G, G, G) float occupancy."""
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(batch, views, G, G, G, generator=g) < density).float()


def stream(model: CompletionModel, seq: torch.Tensor) -> torch.Tensor:
    state = model.init_state(seq.shape[0])
    outs = []
    for t in range(seq.shape[1]):
        logits, state = model.step(state, seq[:, t])
        outs.append(logits)
    return torch.stack(outs, dim=1)


@pytest.fixture(params=VARIANTS, ids=IDS)
def tiny_model(request: pytest.FixtureRequest) -> CompletionModel:
    kind, kernel, rotation = request.param
    return scrambled(tiny_config(kind, kernel, value_rotation=rotation))


# ---- the streaming contract -----------------------------------------------------------------


@torch.no_grad()
def test_streaming_equals_parallel(tiny_model: CompletionModel) -> None:
    seq = random_views(2, 5)
    parallel = tiny_model(seq)
    assert parallel.shape == (2, 5, G, G, G) and parallel.dtype == torch.float32
    assert parallel.std() > 0.3  # non-trivial logits, so atol 1e-5 is a real check
    torch.testing.assert_close(stream(tiny_model, seq), parallel, atol=ATOL, rtol=0)


@torch.no_grad()
def test_appending_views_never_changes_earlier_outputs(tiny_model: CompletionModel) -> None:
    seq = random_views(2, 6)
    prefix = tiny_model(seq[:, :3])
    other_future = torch.cat((seq[:, :3], random_views(2, 3, seed=7, density=0.5)), dim=1)
    torch.testing.assert_close(tiny_model(seq)[:, :3], prefix, atol=ATOL, rtol=0)
    torch.testing.assert_close(tiny_model(other_future)[:, :3], prefix, atol=ATOL, rtol=0)


@torch.no_grad()
def test_earlier_views_reach_later_outputs_except_single_view(tiny_model: CompletionModel) -> None:
    seq = random_views(1, 4)
    changed = seq.clone()
    changed[:, 0] = random_views(1, 1, seed=3)[:, 0]
    effect = (tiny_model(changed)[:, 3] - tiny_model(seq)[:, 3]).abs().max().item()
    if tiny_model.config.kind == "single_view":
        assert effect == 0.0
    else:
        assert effect > 1e-3  # far above the 1e-5 float noise


@torch.no_grad()
def test_view_index_matters_for_attention_models() -> None:
    """Positional encoding: the same frame repeated gives different outputs at different t."""
    model = scrambled(tiny_config("mvp"))
    seq = random_views(1, 1).expand(1, 3, G, G, G)
    out = model(seq)
    assert (out[:, 1] - out[:, 2]).abs().max() > 1e-3
    with pytest.MonkeyPatch.context() as patch:  # without the encoding, identical frames give
        patch.setattr(AttentionTower, "_position", lambda self, x, positions: x)  # equal values
        out = model(seq)
    torch.testing.assert_close(out[:, 1], out[:, 2], atol=ATOL, rtol=0)


@torch.no_grad()
def test_step_leaves_the_given_state_untouched_and_advance_matches_step() -> None:
    for kind in ("mvp", "mvt", "lstm"):
        model = scrambled(tiny_config(kind))
        seq = random_views(1, 3)
        state = model.init_state(1)
        _, state = model.step(state, seq[:, 0])
        kept = {k: v.clone() for k, v in state.items()}
        logits_a, after_step = model.step(state, seq[:, 1])
        logits_b, _ = model.step(state, seq[:, 1])  # the same state can be stepped twice
        assert torch.equal(logits_a, logits_b)
        assert all(torch.equal(state[k], kept[k]) for k in kept)
        after_advance = model.advance(state, seq[:, 1])
        assert after_advance.keys() == after_step.keys()
        for key in after_step:
            torch.testing.assert_close(after_advance[key], after_step[key], atol=1e-6, rtol=0)


# ---- state size and serialisation -------------------------------------------------------------


@torch.no_grad()
def test_mvp_state_size_is_independent_of_views_and_mvt_cache_grows() -> None:
    g = torch.Generator().manual_seed(0)
    frames = (torch.rand(4, 1, G, G, G, generator=g) < 0.05).float()
    mvp = build_model(tiny_config("mvp")).eval()
    state = mvp.init_state(1)
    _, state = mvp.step(state, frames[0])
    size_1, tensors_1 = len(state_to_bytes(state)), state_nbytes(state)
    shapes_1 = {k: v.shape for k, v in state.items()}
    for t in range(1, 999):
        state = mvp.advance(state, frames[t % 4])
    logits, state = mvp.step(state, frames[3])
    assert int(state["t"]) == 1000
    assert torch.isfinite(logits).all()
    assert len(state_to_bytes(state)) == size_1
    assert state_nbytes(state) == tensors_1
    assert {k: v.shape for k, v in state.items()} == shapes_1
    assert state["t"].shape == ()  # the view counter is a scalar

    mvt = build_model(tiny_config("mvt")).eval()
    state = mvt.init_state(1)
    sizes = []
    for t in range(3):
        _, state = mvt.step(state, frames[t])
        sizes.append(state_nbytes(state))
    assert sizes[0] < sizes[1] < sizes[2]
    assert state["layer0.k"].shape[2] == 3


@torch.no_grad()
def test_state_bytes_round_trip_gives_identical_outputs(tiny_model: CompletionModel) -> None:
    seq = random_views(2, 5)
    state = tiny_model.init_state(2)
    for t in range(3):
        _, state = tiny_model.step(state, seq[:, t])
    data = state_to_bytes(state)
    assert isinstance(data, bytes)
    restored = state_from_bytes(data)
    assert restored.keys() == state.keys()
    for key in state:
        assert restored[key].dtype == state[key].dtype and torch.equal(restored[key], state[key])
    plain = torch.load(io.BytesIO(data), weights_only=True)  # what a service store would do
    assert plain.keys() == state.keys()
    for t in range(3, 5):
        logits_a, state = tiny_model.step(state, seq[:, t])
        logits_b, restored = tiny_model.step(restored, seq[:, t])
        assert torch.equal(logits_a, logits_b)


def test_memory_is_carried_in_fp32() -> None:
    state = build_model(tiny_config("mvp")).init_state(3)
    assert state["layer0.S"].dtype == torch.float32 and state["layer0.S"].shape == (3, 2, 16, 8)
    assert state["layer0.z"].shape == (3, 2, 16)
    relu = build_model(tiny_config("mvp", "relu")).init_state(1)
    assert relu["layer1.S"].shape == (1, 2, 8, 8)  # M = E for the ReLU kernel


# ---- checkpoints ------------------------------------------------------------------------------


@torch.no_grad()
def test_checkpoint_round_trip_gives_identical_outputs(
    tiny_model: CompletionModel, tmp_path: Path
) -> None:
    tiny_model.redraw_features(seed=11)  # the drawn features must travel with the weights
    path = tmp_path / "model.pt"
    save_checkpoint(tiny_model, path, threshold=0.4, val={"camera_pan": 0.9}, views=[3, 6])
    loaded = load_checkpoint(path)
    assert loaded.config == tiny_model.config
    assert not loaded.training
    seq = random_views(2, 4)
    assert torch.equal(loaded(seq), tiny_model(seq))
    assert torch.equal(stream(loaded, seq), stream(tiny_model, seq))
    payload = read_checkpoint(path)
    assert payload["threshold"] == 0.4 and payload["val"] == {"camera_pan": 0.9}
    assert payload["config"] == tiny_model.config.to_dict()
    assert payload["grid"]["shape"] == [G, G, G]
    raw = torch.load(path, weights_only=True)  # plain data only
    assert isinstance(raw["config"], dict)


@torch.no_grad()
def test_half_precision_checkpoint_loads_as_fp32(tmp_path: Path) -> None:
    model = scrambled(tiny_config("mvp"))
    path = tmp_path / "half.pt"
    save_checkpoint(_copy(model).half(), path)
    loaded = load_checkpoint(path)
    assert next(loaded.parameters()).dtype == torch.float32
    seq = random_views(1, 3)
    reference = model(seq)
    assert (loaded(seq) - reference).abs().max() < 0.05 * reference.abs().max()


def _copy(model: CompletionModel) -> CompletionModel:
    clone = build_model(model.config)
    clone.load_state_dict(model.state_dict())
    return clone


def test_load_model_by_name_or_path(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    model = build_model(tiny_config("lstm"))
    save_checkpoint(model, tmp_path / "lstm.pt")
    monkeypatch.setattr(model_module, "WEIGHTS_DIR", tmp_path)
    by_name = load_model("lstm")
    by_path = load_model(tmp_path / "lstm.pt")
    assert by_name.config == by_path.config == model.config
    with pytest.raises(FileNotFoundError, match="available: \\['lstm'\\]"):
        load_model("mvp")
    with pytest.raises(FileNotFoundError):
        load_model(tmp_path / "missing.pt")


def test_checkpoint_rejects_non_plain_extras_and_foreign_files(tmp_path: Path) -> None:
    model = build_model(tiny_config("single_view"))
    with pytest.raises(ValueError, match="only plain data"):
        save_checkpoint(model, tmp_path / "x.pt", out_dir=tmp_path)
    with pytest.raises(ValueError, match="may not be named"):
        save_checkpoint(model, tmp_path / "x.pt", config={})
    torch.save({"state_dict": {}}, tmp_path / "foreign.pt")
    with pytest.raises(ValueError, match="not a completion checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")


# ---- config and input validation -------------------------------------------------------------


def test_config_round_trips_through_a_plain_dict() -> None:
    for name in DEFAULT_CONFIGS:
        config = default_config(name)
        plain = config.to_dict()
        assert isinstance(plain["channels"], list)
        assert ModelConfig.from_dict(plain) == config
    assert default_config("mvp_relu").kernel == "relu"
    assert {default_config(n).kind for n in DEFAULT_CONFIGS} == set(MODEL_KINDS)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"kind": "gru"}, "kind must be one of"),
        ({"kernel": "cos"}, "kernel must be"),
        ({"embed_dim": 18, "n_heads": 4}, "divisible by n_heads"),
        ({"grid_size": 36}, "multiple of"),
        ({"n_features": 0}, "n_features"),
        ({"value_rotation": -1}, "value_rotation must be in"),
        ({"value_rotation": float("nan")}, "value_rotation must be in"),
        ({"kind": "lstm", "value_rotation": 30}, "needs an attention model"),
        ({"kind": "single_view", "value_rotation": 30}, "needs an attention model"),
        ({"embed_dim": 15, "n_heads": 3}, "even embed_dim"),
    ],
)
def test_bad_config_raises(overrides: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        tiny_config(**overrides)  # type: ignore[arg-type]


def test_unknown_names_raise() -> None:
    with pytest.raises(ValueError, match="unknown ModelConfig fields"):
        ModelConfig.from_dict({"kind": "mvp", "dropout": 0.1})
    with pytest.raises(ValueError, match="unknown model name"):
        default_config("transformer")


@torch.no_grad()
def test_bad_inputs_raise_and_bool_inputs_work() -> None:
    model = build_model(tiny_config("mvp"))
    with pytest.raises(ValueError, match=r"\(B, L, G, G, G\)"):
        model(torch.zeros(2, G, G, G))
    with pytest.raises(ValueError, match=r"\(B, G, G, G\)"):
        model.step(model.init_state(1), torch.zeros(1, 32, 32, 32))
    with pytest.raises(ValueError, match="expected"):
        model.step(model.init_state(2), torch.zeros(1, G, G, G))  # batch mismatch
    with pytest.raises(ValueError, match="keys"):
        model.step({"t": torch.tensor(0)}, torch.zeros(1, G, G, G))
    seq = random_views(1, 2)
    torch.testing.assert_close(model(seq.bool()), model(seq), atol=0, rtol=0)


def test_build_is_deterministic_and_uses_no_batch_norm() -> None:
    a, b = build_model(tiny_config("mvp", seed=3)), build_model(tiny_config("mvp", seed=3))
    c = build_model(tiny_config("mvp", seed=4))
    sa, sb, sc = a.state_dict(), b.state_dict(), c.state_dict()
    assert all(torch.equal(sa[k], sb[k]) for k in sa)
    assert not torch.equal(sa["decoder.out.weight"], sc["decoder.out.weight"])
    omega = "tower.blocks.0.attn.features.omega"
    assert torch.equal(sa[omega], sb[omega]) and not torch.equal(sa[omega], sc[omega])
    for kind in MODEL_KINDS:
        model = build_model(tiny_config(kind))
        assert not any(
            isinstance(m, torch.nn.modules.batchnorm._BatchNorm) for m in model.modules()
        )


@torch.no_grad()
def test_redraw_features_changes_only_favor_models() -> None:
    seq = random_views(1, 3)
    mvp = scrambled(tiny_config("mvp"))
    before = mvp(seq)
    mvp.redraw_features(seed=1)
    assert not torch.equal(mvp(seq), before)
    relu = scrambled(tiny_config("mvp", "relu"))
    before = relu(seq)
    relu.redraw_features(seed=1)
    assert torch.equal(relu(seq), before)


def test_sinusoidal_encoding_values() -> None:
    pe = sinusoidal_encoding(torch.tensor([0, 1]), 4, base=100.0)
    expected = torch.tensor([[0.0, 1.0, 0.0, 1.0], [0.8414710, 0.5403023, 0.0998334, 0.9950042]])
    torch.testing.assert_close(pe, expected)


# ---- training ----------------------------------------------------------------------------------


def box_sequences(batch: int, views: int, *, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Random solid boxes; each view sees a random half of the box's front (min-z) face.

    Returns inputs, targets: (B, L, G, G, G) float.
    """
    g = torch.Generator().manual_seed(seed)
    inputs = torch.zeros(batch, views, G, G, G)
    targets = torch.zeros(batch, views, G, G, G)
    for b in range(batch):
        lo = torch.randint(4, 16, (3,), generator=g)
        hi = lo + torch.randint(8, 20, (3,), generator=g)
        i0, j0, k0 = lo.tolist()
        i1, j1, k1 = hi.tolist()
        targets[b, :, i0:i1, j0:j1, k0:k1] = 1.0
        for t in range(views):
            keep = (torch.rand(i1 - i0, j1 - j0, generator=g) < 0.5).float()
            inputs[b, t, i0:i1, j0:j1, k0] = keep
    return inputs, targets


def test_tiny_model_learns_boxes() -> None:
    torch.manual_seed(0)
    model = build_model(tiny_config("mvp", channels=(4, 8, 8), embed_dim=32, n_layers=1))
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-3)
    x_eval, y_eval = box_sequences(4, 3, seed=100)

    def eval_loss() -> float:
        with torch.no_grad():
            return F.binary_cross_entropy_with_logits(model(x_eval), y_eval).item()

    before = eval_loss()
    for step in range(25):
        x, y = box_sequences(4, 3, seed=step)
        loss = F.binary_cross_entropy_with_logits(model(x), y)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    after = eval_loss()
    assert after < 0.6 * before, (before, after)


def test_single_frame_convolution_fast_path_matches_the_reference() -> None:
    conv = model_module.Conv3d(3, 5, 3, stride=2, padding=1)
    x = torch.randn(1, 3, 10, 10, 10)
    reference = torch.nn.functional.conv3d(x, conv.weight, conv.bias, stride=2, padding=1)
    with torch.no_grad():
        torch.testing.assert_close(conv(x), reference, atol=1e-5, rtol=1e-5)
    assert conv(x).requires_grad  # with gradients the ordinary path runs


def test_local_input_replaces_what_the_local_tower_sees():
    """``forward(seq, local=...)`` (training's --blank-local): the local tower and the raw-input
    skip take ``local``, the context tower still takes ``seq``."""
    torch.manual_seed(0)
    seq = (torch.rand(1, 3, 40, 40, 40) > 0.9).float()
    blank = torch.zeros_like(seq)
    single = build_model(tiny_config("single_view")).eval()
    mvp = build_model(default_config("mvp")).eval()  # tiny channels can leave no live path
    with torch.no_grad():
        torch.testing.assert_close(single(seq, local=seq), single(seq))
        torch.testing.assert_close(single(seq, local=blank), single(blank))  # no context tower
        for p in mvp.bridge.expand.parameters():
            p.normal_()  # the context path starts at zero: open it
        assert not torch.allclose(mvp(seq, local=blank), mvp(blank))  # the context saw seq
    with pytest.raises(ValueError, match="local must have seq's shape"):
        mvp(seq, local=blank[:, :2])


def test_warm_start_from_the_same_model_loads_it_whole(tmp_path):
    from completion.train import warm_start

    source = build_model(tiny_config("mvp", seed=3))
    save_checkpoint(source, tmp_path / "mvp.pt")
    target = build_model(tiny_config("mvp", seed=4))
    warm_start(target, tmp_path / "mvp.pt")
    for (name, a), b in zip(source.state_dict().items(), target.state_dict().values(),
                            strict=True):
        torch.testing.assert_close(a.float(), b.float(), msg=name)
    rotary = build_model(tiny_config("mvp", seed=4, value_rotation=30))
    warm_start(rotary, tmp_path / "mvp.pt")  # rotary values have no weights: loads whole
    for (name, a), b in zip(source.state_dict().items(), rotary.state_dict().values(),
                            strict=True):
        torch.testing.assert_close(a.float(), b.float(), msg=name)


@torch.no_grad()
def test_warm_start_across_kinds_takes_every_shared_tensor(tmp_path):
    """The recipe that trains all six from one network: a multi-view checkpoint gives
    Single-View its local U-Net, MVT MVP's attention weights, an LSTM all but its block (whose
    output layer then starts at zero, so it begins as the U-Net alone)."""
    from completion.train import warm_start

    source = build_model(tiny_config("mvp", seed=3))
    for p in source.bridge.expand.parameters():
        p.normal_()  # a trained context path: not zero
    save_checkpoint(source, tmp_path / "mvp.pt")
    mine = {k: v.float() for k, v in source.state_dict().items()}

    single = build_model(tiny_config("single_view", seed=4))
    assert warm_start(single, tmp_path / "mvp.pt") == []
    for name, value in single.state_dict().items():
        torch.testing.assert_close(value, mine[name], msg=name)

    mvt = build_model(tiny_config("mvt", seed=4, qk_norm=True))
    assert warm_start(mvt, tmp_path / "mvp.pt") == []  # MVP's random features are a buffer
    for name, value in mvt.state_dict().items():
        torch.testing.assert_close(value, mine[name], msg=name)

    lstm = build_model(tiny_config("lstm", seed=4))
    fresh = warm_start(lstm, tmp_path / "mvp.pt")
    assert fresh and all(name.startswith("tower.lstm.") for name in fresh)
    assert not lstm.bridge.expand.weight.any()  # the new block's path starts closed
    seq = (torch.rand(1, 3, 40, 40, 40, generator=torch.Generator().manual_seed(0)) > 0.9).float()
    torch.testing.assert_close(lstm.eval()(seq), single.eval()(seq))  # the U-Net alone

    narrow = build_model(tiny_config("mvp", channels=(4, 8, 16)))
    with pytest.raises(ValueError, match="shares no U-Net"):
        warm_start(narrow, tmp_path / "mvp.pt")


def test_config_overrides_parse_numbers_tuples_and_booleans():
    from completion.train import _overrides

    assert _overrides("value_rotation=30,qk_norm=true,channels=8:16:32,kernel=relu") == {
        "value_rotation": 30, "qk_norm": True, "channels": (8, 16, 32), "kernel": "relu"}
    assert _overrides("qk_norm=False") == {"qk_norm": False}


@torch.no_grad()
def test_rotary_values_turn_each_past_value_by_the_view_offset() -> None:
    """Exact attention with rotary values: y_t = out(Σ_s w_ts · R(θ_s − θ_t) v_s), where
    R turns channel pair i by (i mod 7) · 30° per view; and rotate_pairs inverts exactly."""
    from completion.towers import CausalSelfAttention, rotate_pairs, value_angles

    config = tiny_config("mvt", value_rotation=30, embed_dim=32, n_heads=2)
    layer = CausalSelfAttention(config, mechanism="exact")
    g = torch.Generator().manual_seed(0)
    x = torch.randn(1, 6, 1, 32, generator=g)  # (B, L, P, D), one token per view
    q, k, v = (t[0, :, 0].transpose(0, 1) for t in layer._heads(x))  # (H, L, E)
    e = config.embed_dim // config.n_heads
    angles = value_angles(torch.arange(6), e, 30.0)  # (L, E/2)
    assert torch.allclose(angles[1, :8], torch.tensor([0, 1, 2, 3, 4, 5, 6, 0.0]) * torch.pi / 6)
    scores = (q @ k.transpose(-1, -2)) * e**-0.5
    weights = scores.masked_fill(torch.ones(6, 6).triu(1).bool(), float("-inf")).softmax(-1)
    expected = torch.zeros_like(v)
    for t in range(6):
        for s_ in range(t + 1):
            turned = rotate_pairs(v[:, s_], angles[s_] - angles[t])
            expected[:, t] += weights[:, t, s_, None] * turned
    expected = layer.out(expected.transpose(0, 1).flatten(1))
    torch.testing.assert_close(layer(x)[0, :, 0], expected, atol=1e-5, rtol=0)
    torch.testing.assert_close(rotate_pairs(rotate_pairs(v, angles), -angles), v, atol=1e-6, rtol=0)
