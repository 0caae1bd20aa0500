"""What a perfect memory would add on slide behind: each model's Jaccard beside the Jaccard of
its prediction united with the sliding object's true voxels (the object the memory should keep
once it is behind the other), and the share of those voxels its prediction holds (recall), on
the sequences the evaluation draws.

The difference is the memory's headroom: how much of the slide-behind score a model could still
gain by remembering the hidden object exactly, with its own completion of everything else. Read
it beside MVP minus Single-View: the share of the headroom a memory has taken.

A memory can only carry what the model made of the slider while it saw it, so a third column,
"own slider moved", is the ideal transport of the model's own completion: its predicted voxels
within two voxels of the slider's truth in the first view, moved by the slider's true translation
into each view and united with the prediction there. It bounds what a memory of that model's
completion quality can reach; beyond it the completion itself must get better.
``--shift-quantum Q`` rounds that translation to a multiple of Q voxels (a memory that places the
slider only to within Q/2 voxels; Q = 8 is a whole place of the 5³ bottleneck): how precisely a
memory must put the shape down for it to pay.

Two more columns say what a model draws where the slider is: "slider precision", the share of its
predicted voxels within three voxels of the slider (the front object's voxels left out) that are
the slider's, and "slider |dx|", how far along x (voxels) their centre lies from the slider's.
For a model with a shift memory (``ModelConfig.shift_heads``) a line per model says how far
from the slider's true move along x its best head puts what the first view wrote, and another
its Jaccard with every head standing exactly at the slider's centre in every view (write and
read, :func:`standing_at`): what a perfectly placed memory would add to the model as trained.

Two columns ask whether fusing what the views *saw* of the slider could beat carrying one view's
completion: the model run on inputs to which the slider's observed surface voxels are added,
moved by its true translation, from the first view only ("+ first surface moved") or from every
view so far ("+ all surfaces moved": registered fusion of the slider's observations). Where the
second is no better than the first, the few degrees the slider turns while it moves across the
image tell a completer nothing more, and a memory of observations cannot beat one of completions.
"+ completions averaged" unites each view's prediction with the mean of the model's own
probabilities near the slider over the views so far that show it (at least half the surface of
the first), moved: an exact memory that averages every view's completion of the slider.
"slider completed in view 0" is the Jaccard of each model's completion of the slider in the first
view (its voxels within two voxels of the slider) with the slider's truth: all a memory can carry;
a last line gives the slider's median size in that view's grid.

    python -m completion.headroom      # shipped single_view and mvp, test split, seed 0
    python -m completion.headroom --models mvp,runs/w/mvp.pt --split val --count 5
    python -m completion.headroom --models mvp --shift-quantum 4   # transport to within 2 voxels
    python -m completion.headroom --models single_view,mvp --split val --count 24 --threshold 0.6
"""

from __future__ import annotations

import argparse
import contextlib
import sys

import numpy as np
import torch
from scipy import ndimage

from completion import grid
from completion.cli import integer_at_least
from completion.model import load_model
from completion.objects import SPLITS
from completion.scenes import VIEWS, make_sequence, object_meshes_in_camera
from completion.shift import frame_at

SLIDING = 1  # the sliding object's index in a slide-behind sequence (the front one is 0)
NEAR = 2  # voxels: how far from the slider's truth a predicted voxel still counts as its completion
AROUND = 3  # voxels: the neighbourhood of the slider whose predicted voxels the precision judges


def slider_index(seq, view: int) -> np.ndarray:
    """(3,) float: the sliding object's centre in ``view``'s grid, in voxels."""
    centre = np.asarray(seq.meta["object_to_world"][view][SLIDING], dtype=np.float64)[:, 3]
    in_camera = np.linalg.solve(seq.camera_to_world[view], centre)[:3]
    return grid.points_to_indices(in_camera[None], seq.grid_to_camera[view], rounded=False)[0]


def slider_move(seq, view: int) -> np.ndarray:
    """(3,) float: the voxels by which the sliding object moved between view 0 and ``view``,
    each in its own view's grid (the grids share a pitch and axes: the camera of slide behind
    stands still)."""
    return slider_index(seq, view) - slider_index(seq, 0)


@contextlib.contextmanager
def standing_at(model: torch.nn.Module, cells: torch.Tensor):
    """Within the block, every head of the model's shift memory writes and reads each frame
    exactly at ``cells[frame]`` along i (cells of its level, fractions allowed): given the
    slider's centre, a transport of everything written by the slider's true move. How much a
    perfectly placed memory would add to the model as trained."""
    memory = model.shift_memory

    def exact(_cells, _frames):
        frame = frame_at(cells[:, None].expand(-1, memory.heads).float(), memory.omega)
        return frame, frame

    memory._frames = exact
    try:
        yield
    finally:
        del memory._frames


def slider_shift(seq, view: int) -> np.ndarray:
    """(3,) int: :func:`slider_move` rounded to whole voxels."""
    return np.round(slider_move(seq, view)).astype(int)


def shift_move_error(model: torch.nn.Module, x: torch.Tensor, move_x: np.ndarray) -> np.ndarray:
    """(H, L): per head of the model's shift memory (``ModelConfig.shift_heads``) and view v,
    |p_read(v) − p_write(0) − move_x[v]| in voxels: how far from the slider's true move along x
    the memory puts what the first view wrote. (0, L) for a model without one."""
    memory = getattr(model, "shift_memory", None)
    if memory is None:
        return np.zeros((0, len(move_x)))
    with torch.no_grad():
        frames = x.flatten(0, 1)
        level = model.context_encoder(frames)[0]
        p_write, p_read = (2 * p.T.double().numpy() for p in memory.references(level, frames))
    return np.abs(p_read - p_write[:, :1] - np.asarray(move_x)[None])  # 2 voxels a cell


def quantised(shift: np.ndarray, quantum: int) -> np.ndarray:
    """``shift`` rounded to the nearest multiple of ``quantum`` voxels, per axis."""
    return (np.round(np.asarray(shift) / quantum) * quantum).astype(int)


def moved(voxels: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """Boolean grid ``voxels`` translated by ``shift`` voxels; what leaves the grid is dropped."""
    return ndimage.shift(voxels.astype(np.uint8), shift, order=0, mode="constant", cval=0) > 0


def slider_seen(inputs: np.ndarray, sliding: np.ndarray) -> np.ndarray:
    """(L, 40, 40, 40) bool: the slider's observed voxels, the input voxels within one voxel
    of its truth."""
    return inputs & np.stack([ndimage.binary_dilation(s) for s in sliding])


def observed_surfaces_moved(inputs: np.ndarray, sliding: np.ndarray, shifts: list,
                            *, every_view: bool) -> np.ndarray:
    """(L, 40, 40, 40) bool: ``inputs`` with the slider's observed voxels (:func:`slider_seen`)
    of view 0 (or of every view u ≤ v) moved into each view v by the slider's translation
    between them."""
    seen = slider_seen(inputs, sliding)
    out = inputs.copy()
    for v in range(len(inputs)):
        for u in range(v + 1 if every_view else 1):
            out[v] |= moved(seen[u], np.asarray(shifts[v]) - np.asarray(shifts[u]))
    return out


def completions_averaged(probability: np.ndarray, sliding: np.ndarray, inputs: np.ndarray,
                         shifts: list, threshold: float) -> np.ndarray:
    """(L, 40, 40, 40) bool: each view's prediction united with the mean of the model's
    probabilities near the slider (within two voxels of it) over the views u ≤ v in which the
    slider shows at least half the surface it shows in view 0, each moved by the slider's
    translation from u to v, decided at ``threshold``: an exact memory that averages what every
    view completed of the slider."""
    seen = slider_seen(inputs, sliding).sum((1, 2, 3))
    near = [probability[u] * ndimage.binary_dilation(sliding[u], iterations=NEAR)
            for u in range(len(inputs))]  # fmt: skip
    out = probability >= threshold
    for v in range(len(inputs)):
        views = [u for u in range(v + 1) if seen[u] >= 0.5 * seen[0]]
        carried = [ndimage.shift(near[u], np.asarray(shifts[v]) - np.asarray(shifts[u]), order=0)
                   for u in views]  # fmt: skip
        out[v] |= np.mean(carried, axis=0) >= threshold
    return out


def _offset_x(drawn: np.ndarray, sliding: np.ndarray) -> float:
    """|mean i of ``drawn`` − mean i of ``sliding``| in voxels; NaN if either is empty."""
    if not drawn.any() or not sliding.any():
        return float("nan")
    return float(abs(np.nonzero(drawn)[0].mean() - np.nonzero(sliding)[0].mean()))


def _mean_over_sequences(values: list) -> np.ndarray:
    """Per view, the mean over the sequences that have a value (NaN where none has)."""
    a = np.asarray(values, dtype=np.float64)
    have = ~np.isnan(a)
    return np.where(have.any(0), np.where(have, a, 0).sum(0) / np.maximum(have.sum(0), 1), np.nan)


def headroom(
    models: dict[str, torch.nn.Module], *, split: str = "test", count: int = 10, seed: int = 0,
    views: int = VIEWS, shift_quantum: int = 1,
) -> dict:
    """Per model: mean Jaccard per view (over ``count`` sequences) of its prediction at its own
    threshold ("alone"), of that prediction united with the sliding object's voxels
    ("with_sliding_truth") or with its own first-view completion of the slider moved where the
    slider is ("own_slider_moved"; the translation rounded to a multiple of ``shift_quantum``
    voxels), and the share of the sliding object's voxels it predicts
    ("sliding_recall"), the share of its voxels around the slider that are the slider's
    ("sliding_precision") and the x distance of their centre from the slider's
    ("sliding_offset_x", NaN where it predicts none there); the model run on inputs with the
    slider's observed surface moved in from the first view or from every view so far
    ("first_surface_moved", "all_surfaces_moved": :func:`observed_surfaces_moved`), its
    prediction with every view's completion of the slider averaged in ("completions_averaged":
    :func:`completions_averaged`), and its
    completion of the slider in the first view against the slider's truth ("first_view_slider",
    one value); per view the sliding object's share of the target, and the slider's median
    extent along i, j, k and voxel count in the first view ("slider_size")."""
    keys = ("alone", "with_sliding_truth", "own_slider_moved", "sliding_recall",
            "sliding_precision", "sliding_offset_x", "shift_move_error", "shift_exact",
            "first_surface_moved", "all_surfaces_moved", "first_view_slider",
            "completions_averaged")
    rows = {name: {k: [] for k in keys} for name in models}
    share, still, size = [], [], []
    for index in range(count):
        seq = make_sequence("slide_behind", split, index, seed, views=views)
        x = torch.from_numpy(seq.inputs[None].astype(np.float32))
        sliding = []
        for v in range(len(seq)):
            mesh = object_meshes_in_camera(seq, v)[SLIDING]
            voxels = grid.voxelize_mesh(mesh.vertices, mesh.faces, seq.grid_to_camera[v])
            sliding.append(voxels & seq.targets[v])
        sliding = np.stack(sliding)
        share.append(sliding.sum((1, 2, 3)) / seq.targets.sum((1, 2, 3)))
        size.append([np.ptp(i) + 1 for i in np.nonzero(sliding[0])] + [sliding[0].sum()])
        near_first = ndimage.binary_dilation(sliding[0], iterations=NEAR)
        around = [ndimage.binary_dilation(s, iterations=AROUND) & ~(t & ~s)
                  for s, t in zip(sliding, seq.targets, strict=True)]
        shifts = [quantised(slider_shift(seq, v), shift_quantum) for v in range(len(seq))]
        centre_x = np.array([slider_index(seq, v)[0] for v in range(len(seq))])  # voxels
        move_x = centre_x - centre_x[0]
        cells = torch.from_numpy(centre_x / 2)  # where the slider is, in 2-voxel cells
        still.append(np.abs(move_x))
        fused = {key: torch.from_numpy(observed_surfaces_moved(
            seq.inputs, sliding, shifts, every_view=every)[None].astype(np.float32))
            for key, every in (("first_surface_moved", False), ("all_surfaces_moved", True))}
        for name, model in models.items():
            with torch.no_grad():
                probability = torch.sigmoid(model(x))[0].numpy()
            threshold = getattr(model, "threshold", 0.5)
            pred = probability >= threshold
            rows[name]["alone"].append(grid.jaccard(pred, seq.targets))
            rows[name]["completions_averaged"].append(grid.jaccard(
                completions_averaged(probability, sliding, seq.inputs, shifts, threshold),
                seq.targets))  # fmt: skip
            rows[name]["with_sliding_truth"].append(grid.jaccard(pred | sliding, seq.targets))
            own = pred[0] & near_first  # the model's completion of the slider in the first view
            rows[name]["first_view_slider"].append([grid.jaccard(own, sliding[0])])
            carried = np.stack([pred[v] | moved(own, shifts[v]) for v in range(len(seq))])
            rows[name]["own_slider_moved"].append(grid.jaccard(carried, seq.targets))
            found = (pred & sliding).sum((1, 2, 3)) / np.maximum(sliding.sum((1, 2, 3)), 1)
            rows[name]["sliding_recall"].append(found)
            drawn = [pred[v] & around[v] for v in range(len(seq))]
            rows[name]["sliding_precision"].append(
                [(d & s).sum() / max(d.sum(), 1) for d, s in zip(drawn, sliding, strict=True)])
            rows[name]["sliding_offset_x"].append([_offset_x(d, s) for d, s in
                                                   zip(drawn, sliding, strict=True)])
            rows[name]["shift_move_error"].append(shift_move_error(model, x, move_x))
            for key, inputs in fused.items():
                with torch.no_grad():
                    decided = torch.sigmoid(model(inputs))[0].numpy() >= threshold
                rows[name][key].append(grid.jaccard(decided, seq.targets))
            if getattr(model, "shift_memory", None) is not None:
                with torch.no_grad(), standing_at(model, cells):
                    exact = torch.sigmoid(model(x))[0].numpy() >= threshold
                rows[name]["shift_exact"].append(grid.jaccard(exact, seq.targets))
    per_view = {
        name: {k: _mean_over_sequences(v).round(4).tolist() if v else [] for k, v in r.items()}
        for name, r in rows.items()
    }
    return {"split": split, "count": count, "seed": seed, "shift_quantum": shift_quantum,
            "per_view": per_view,
            "slider_move_x": np.mean(still, axis=0).round(4).tolist(),
            "sliding_share": np.mean(share, axis=0).round(4).tolist(),
            "slider_size": np.median(size, axis=0).tolist()}  # fmt: skip


def _probability(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1), got {text!r}") from None
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"expected a number in (0, 1), got {value}")
    return value


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m completion.headroom",
        description="Slide behind: each model's Jaccard, and with the sliding object's true "
        "voxels added to its prediction (what a perfect memory of the hidden object would add).",
    )
    p.add_argument("--models", default="single_view,mvp",
                   help="comma-separated shipped names or checkpoint files")  # fmt: skip
    p.add_argument("--split", choices=SPLITS, default="test")
    p.add_argument("--count", type=integer_at_least(1), default=10, help="sequences")
    p.add_argument("--seed", type=int, default=0, help="scene seed (the evaluation's: 0)")
    p.add_argument("--threshold", type=_probability, default=None, metavar="T",
                   help="decide occupancy at T for every model (default: each model's own)")
    p.add_argument("--shift-quantum", type=integer_at_least(1), default=1, metavar="Q",
                   help="round the slider's translation in '+ own slider moved' to a multiple "
                   "of Q voxels (default 1: exact)")  # fmt: skip
    args = p.parse_args(argv)
    names = [n.strip() for n in args.models.split(",") if n.strip()]
    if not names:
        p.error("--models names no model")
    try:
        models = {n: load_model(n).eval() for n in names}
    except FileNotFoundError as exc:
        p.error(str(exc))
    if args.threshold is not None:
        for model in models.values():
            model.threshold = args.threshold
    out = headroom(models, split=args.split, count=args.count, seed=args.seed,
                   shift_quantum=args.shift_quantum)
    print(f"slide behind, {args.split} split, {args.count} sequences, seed {args.seed}, slider "
          f"moved in steps of {args.shift_quantum} voxel(s): mean Jaccard over the views "
          "(last six views)")  # fmt: skip
    print(f"{'model':>24}  {'alone':>15}  {'+ sliding truth':>15}  {'headroom':>8}  "
          f"{'+ own slider moved':>18}  {'sliding recall':>15}  {'slider precision':>16}  "
          f"{'slider |dx|':>13}")  # fmt: skip
    for name, r in out["per_view"].items():
        alone, full = np.array(r["alone"]), np.array(r["with_sliding_truth"])
        own, found = np.array(r["own_slider_moved"]), np.array(r["sliding_recall"])
        prec, dx = np.array(r["sliding_precision"]), np.array(r["sliding_offset_x"])
        print(f"{name:>24}  {alone.mean():.3f} ({alone[-6:].mean():.3f})  "
              f"{full.mean():.3f} ({full[-6:].mean():.3f})  {full.mean() - alone.mean():+.3f}  "
              f"   {own.mean():.3f} ({own[-6:].mean():.3f})  "
              f"   {found.mean():.3f} ({found[-6:].mean():.3f})"
              f"    {prec.mean():.3f} ({prec[-6:].mean():.3f})"
              f"  {_mean_over_sequences(dx):.2f} ({_mean_over_sequences(dx[-6:]):.2f})")
    print(f"{'model':>24}  {'+ first surface moved':>21}  {'+ all surfaces moved':>20}  "
          f"{'+ completions averaged':>22}  {'slider completed in view 0':>26}")  # fmt: skip
    for name, r in out["per_view"].items():
        first, every = np.array(r["first_surface_moved"]), np.array(r["all_surfaces_moved"])
        mean = np.array(r["completions_averaged"])
        print(f"{name:>24}  {first.mean():.3f} ({first[-6:].mean():.3f})      "
              f"{every.mean():.3f} ({every[-6:].mean():.3f})    "
              f"{mean.mean():.3f} ({mean[-6:].mean():.3f})  "
              f"{r['first_view_slider'][0]:>26.3f}")  # fmt: skip
    print(f"sliding object's share of the target: {np.mean(out['sliding_share']):.3f}")
    *extent, voxels = out["slider_size"]
    print("the slider in view 0 (medians): {:g} x {:g} x {:g} voxels across, {:g} voxels".format(
        *extent, voxels))  # fmt: skip
    still = np.array(out["slider_move_x"])
    for name, r in out["per_view"].items():
        error = np.array(r["shift_move_error"])  # (H, L)
        if error.size:
            h = int(error[:, -6:].mean(1).argmin())
            print(f"{name}: shift memory head {h} (of {len(error)}) moves what the first view "
                  f"wrote to within {error[h, -6:].mean():.2f} voxels of the slider's move along "
                  f"x in the last six views ({error[h].mean():.2f} over all); standing still: "
                  f"{still[-6:].mean():.2f} ({still.mean():.2f})")
            exact, alone = np.array(r["shift_exact"]), np.array(r["alone"])
            print(f"{name}: with every head standing exactly at the slider (write and read): "
                  f"{exact.mean():.3f} ({exact[-6:].mean():.3f}) against "
                  f"{alone.mean():.3f} ({alone[-6:].mean():.3f}) as learned")
    return 0


if __name__ == "__main__":
    sys.exit(main())
