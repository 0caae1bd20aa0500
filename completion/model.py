"""Shape-completion networks: Single-View, MVP (causal Performer memory), MVT and LSTM baselines.

Axis letters used in shape comments and docstrings:

    B  batch (sequences)                 L  views in a sequence (time)
    N  frames in one flat batch (B·L)    G  grid side (40); a grid is (G, G, G) indexed (i, j, k)
    C  conv channels                     D  embedding size
    H  attention heads                   E  head size (D / H)
    M  random features (FAVOR+) or E (ReLU kernel)
    T  views held in an MVT key/value cache (grows with the stream)

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
frame's bottleneck volume into one token (:class:`Bridge`), a causal sequence model (Performer,
exact Transformer or LSTM: :mod:`completion.towers`; fp32 even under bf16 autocast) relates it
to the past, and its output, mapped back to a bottleneck volume, is added to the local
bottleneck before decoding (the paper adds the two towers' embeddings). No normalisation
statistic crosses frames (LayerNorm per token only).
"""

from __future__ import annotations

import io
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch import Tensor, nn

from completion.config import ModelConfig
from completion.conv import Conv3d
from completion.performer import FeatureMap
from completion.towers import AttentionTower, LSTMTower

State = dict[str, Tensor]
KV_CACHE_SUFFIXES = (".k", ".v")

CHECKPOINT_FORMAT = "mvp-grasp/completion-checkpoint"
CHECKPOINT_VERSION = 3
"""3: the config holds only the fields of :class:`ModelConfig` that the shipped models use."""

GRID_CONVENTION: dict[str, Any] = {
    "shape": [40, 40, 40],
    "axes": "grid index (i, j, k) along camera (x, y, z), OpenCV optical frame",
    "fit": "bbox centre of observed points at index (20, 20, 18), resolution = max extent / 32",
    "inputs": "observed surface points voxelized, occupied = 1",
    "targets": "complete object(s), solid",
}
"""Stored in every checkpoint (docs/design.md §3); training may overwrite it via ``grid=...``."""

WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"


# --------------------------------------------------------------------------------------------
# Shared encoder / decoder
# --------------------------------------------------------------------------------------------


class Encoder(nn.Module):
    """Down path of the 3-D U-Net, one frame at a time: (N, G, G, G) -> one feature volume per
    level, finest first: [(N, C0, G/2, G/2, G/2), (N, C1, G/4, …), …, (N, Cn, G/2^n, …)].

    Each level is a stride-2 conv (so nothing but the decoder's output layer runs at G³) and a
    same-size conv, each followed by ReLU.
    """

    def __init__(self, config: ModelConfig) -> None:
        super().__init__()
        self.levels = nn.ModuleList()
        c_in = input_channels(config)
        for c_out in config.channels:
            self.levels.append(
                nn.Sequential(*_conv(c_in, c_out, stride=2), *_conv(c_out, c_out))
            )
            c_in = c_out

    def forward(self, grids: Tensor) -> list[Tensor]:
        """grids: (N, C, G, G, G), C = :func:`input_channels`."""
        # channels-last: oneDNN's 3-D convolutions with few channels run 5-15x faster on the CPU
        x = grids.contiguous(memory_format=torch.channels_last_3d)
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
        self.bottom = nn.Sequential(*_conv(chans[-1], chans[-1]))
        self.ups = nn.ModuleList()
        self.fuse = nn.ModuleList()
        for c_deep, c_skip in zip(chans[:0:-1], chans[-2::-1], strict=True):
            self.ups.append(nn.ConvTranspose3d(c_deep, c_skip, 2, stride=2))
            self.fuse.append(nn.Sequential(*_conv(2 * c_skip, c_skip)))
        self.top = nn.ConvTranspose3d(chans[0], config.top_channels, 2, stride=2)
        self.out = Conv3d(config.top_channels + input_channels(config), 1, 3, padding=1)

    def forward(self, bottom: Tensor, skips: list[Tensor], grids: Tensor) -> Tensor:
        x = self.bottom(bottom)
        for up, fuse, skip in zip(self.ups, self.fuse, skips[-2::-1], strict=True):
            x = fuse(torch.cat((torch.relu(up(x)), skip), dim=1))
        x = torch.relu(self.top(x))
        x = torch.cat((x, grids.to(x.dtype)), dim=1)
        x = x.contiguous(memory_format=torch.channels_last_3d)
        return self.out(x).squeeze(1)  # (N, G, G, G)


def widened_inputs(saved: Tensor, own: Tensor) -> Tensor | None:
    """A conv weight (out, in, k, k, k) widened to ``own``'s input channels, the new ones zero;
    None unless only the input channels grew."""
    if saved.ndim != 5 or own.ndim != 5 or saved.shape[0] != own.shape[0]:
        return None
    if saved.shape[2:] != own.shape[2:] or saved.shape[1] >= own.shape[1]:
        return None
    wide = torch.zeros(own.shape, dtype=saved.dtype)
    wide[:, : saved.shape[1]] = saved
    return wide


def input_channels(config: ModelConfig) -> int:
    """Channels of a frame as the U-Net takes it: the view's surface, and with
    ``registered_input`` the surface earlier posed views saw (:mod:`completion.evidence`)."""
    return 2 if config.registered_input else 1


def _conv(c_in: int, c_out: int, *, stride: int = 1) -> list[nn.Module]:
    """Conv 3×3×3 (padding 1: same size at stride 1, halved at stride 2), ReLU."""
    return [Conv3d(c_in, c_out, 3, stride=stride, padding=1), nn.ReLU()]


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

    def token(self, bottom: Tensor) -> Tensor:
        return self.to_token(torch.relu(self.reduce(bottom)).flatten(1)).unsqueeze(1)

    def volume(self, token: Tensor) -> Tensor:
        g = self.g
        x = torch.relu(self.from_token(token.squeeze(1))).view(-1, self.ct, g, g, g)
        return self.expand(x)


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
        self.bridge: Bridge | None = None
        self.tower: AttentionTower | LSTMTower | None = None
        if config.kind != "single_view":
            self.context_encoder = Encoder(config)
            self.bridge = Bridge(config)
            if config.kind == "lstm":
                self.tower = LSTMTower(config)
            else:
                mechanism = "performer" if config.kind == "mvp" else "exact"
                self.tower = AttentionTower(config, mechanism=mechanism, generator=generator)

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

    def forward(self, seq: Tensor, *, local: Tensor | None = None,
                seen: Tensor | None = None) -> Tensor:
        """``local``: what the local tower and the decoder's raw-input skip see instead of
        ``seq`` (same shape); training blanks views there so that the context tower must carry
        the shape (``completion.train --blank-local``). The context tower always sees ``seq``.
        ``seen`` (same shape): with ``registered_input``, the surface earlier posed views saw, in
        each view's grid (None: nothing, as without poses); every tower takes it.
        """
        seq = self._check_grids(seq, ndim=5, what="seq")
        b, n = seq.shape[:2]
        if local is not None:
            local = self._check_grids(local, ndim=5, what="local")
            if local.shape != seq.shape:
                raise ValueError(f"local must have seq's shape {tuple(seq.shape)}, "
                                 f"got {tuple(local.shape)}")
        seen = self._check_seen(seen, seq)
        frames = self._frames(seq.flatten(0, 1), seen)  # (N, C, G, G, G)
        local_frames = frames if local is None else self._frames(local.flatten(0, 1), seen)
        skips = self.encoder(local_frames)  # local tower: this frame alone
        bottom = skips[-1]
        if self.context_encoder is not None:
            tokens = self.bridge.token(self.context_encoder(frames)[-1])  # (N, 1, D)
            tokens = tokens.view(b, n, *tokens.shape[1:])  # (B, L, 1, D)
            with _full_precision(tokens):
                context = self.tower(tokens.float())  # (B, L, 1, D)
            bottom = bottom + self.bridge.volume(context.flatten(0, 1)).to(bottom.dtype)
        logits = self.decoder(bottom, skips, local_frames)  # (N, G, G, G)
        return logits.view(seq.shape)

    def _check_seen(self, seen: Tensor | None, like: Tensor) -> Tensor | None:
        """``seen`` checked against the frames it goes with (flattened to (N, G, G, G))."""
        if seen is None:
            return None
        if not self.config.registered_input:
            raise ValueError("seen needs a model with registered_input (this one takes one "
                             "channel)")
        seen = self._check_grids(seen, ndim=like.ndim, what="seen")
        if seen.shape != like.shape:
            raise ValueError(f"seen must have the frames' shape {tuple(like.shape)}, "
                             f"got {tuple(seen.shape)}")
        return seen.flatten(0, seen.ndim - 4)

    def _frames(self, frames: Tensor, seen: Tensor | None) -> Tensor:
        """(N, G, G, G) -> (N, C, G, G, G): the U-Net's channels (:func:`input_channels`)."""
        if not self.config.registered_input:
            return frames.unsqueeze(1)
        return torch.stack((frames, torch.zeros_like(frames) if seen is None else seen), dim=1)

    # ---- streaming -----------------------------------------------------------------------

    def init_state(self, batch: int) -> State:
        """State before any view: {"t": 0-d int64} plus the tower's memory."""
        if batch < 1:
            raise ValueError(f"batch must be >= 1, got {batch}")
        device = self.decoder.out.weight.device
        state: State = {"t": torch.zeros((), dtype=torch.int64, device=device)}
        if self.tower is not None:
            state |= self.tower.init_state(batch, device=device)
        return state

    def step(self, state: State, frame: Tensor, *,
             seen: Tensor | None = None) -> tuple[Tensor, State]:
        """Consume one view: frame (B, G, G, G) -> (logits (B, G, G, G), new state); ``seen``
        as in :meth:`forward`.

        The given state is not modified, so it can be kept and stepped again.
        """
        frames, volume, new = self._context_step(state, frame, seen)
        skips = self.encoder(frames)
        bottom = skips[-1] if volume is None else skips[-1] + volume.to(skips[-1].dtype)
        return self.decoder(bottom, skips, frames), new

    def advance(self, state: State, frame: Tensor, *, seen: Tensor | None = None) -> State:
        """Consume one view without decoding it: the state :meth:`step` would return, cheaper.

        For catching up on views whose completion is not needed (only the latest one usually is).
        """
        return self._context_step(state, frame, seen)[2]

    def _context_step(self, state: State, frame: Tensor,
                      seen: Tensor | None) -> tuple[Tensor, Tensor | None, State]:
        """One view through the context tower: (the checked frame as the U-Net takes it
        (B, C, G, G, G), the bottleneck volume to add (B, Cn, g, g, g) or None for Single-View,
        the new state)."""
        frame = self._check_grids(frame, ndim=4, what="frame")
        frames = self._frames(frame, self._check_seen(seen, frame))
        self._check_state(state, batch=frame.shape[0])
        new: State = {"t": state["t"] + 1}
        if self.context_encoder is None:
            return frames, None, new
        tokens = self.bridge.token(self.context_encoder(frames)[-1])  # (B, 1, D)
        with _full_precision(tokens):
            context, entries = self.tower.step(tokens.float(), state["t"], state)
        return frames, self.bridge.volume(context), new | entries

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
