"""The shipped weights (completion/weights/): their architecture is the default one, their logits
are pinned, and the recipe that made them is a script whose every training command parses."""

from __future__ import annotations

import os
import shlex
import subprocess
from pathlib import Path

import pytest
import torch

from completion.config import DEFAULT_CONFIGS, ModelConfig
from completion.model import WEIGHTS_DIR, load_model, read_checkpoint
from completion.train import parse_args, run_config

SIX = ("single_view", "mvp", "mvp3", "mvp6", "mvt", "lstm")  # the paper's models
SHIPPED = (*SIX, "mvp_posed")  # and MVP for sessions with camera poses
RECIPE = WEIGHTS_DIR / "recipe.sh"

# mean logit over the three views, the logit at the grid's fit centre (20, 20, 18) in each view,
# and one behind the box (20, 20, 30) in the last view; measured with the weights fine-tuned on
# the cleaned input of a real camera (stage 10 of recipe.sh)
PINNED = {
    "single_view": (-12.351588, (4.08986, 2.41977, 2.51334), -4.63616),
    "mvp": (-14.384725, (4.17911, 3.16378, 3.10348), -3.63521),
    "mvp3": (-14.348511, (3.93236, 3.15850, 2.97552), -3.41705),
    "mvp6": (-14.173649, (4.19814, 3.80899, 3.58903), -3.04147),
    "mvt": (-14.415553, (4.07498, 3.15479, 3.07248), -3.90224),
    "lstm": (-12.577876, (4.23893, 3.31505, 3.29921), -5.91069),
    # stage 12: given the earlier views as what it saw before (see the test)
    "mvp_posed": (-13.200676, (4.05619, 3.77654, 4.29702), -5.19427),
}


def box_views(views: int = 3) -> torch.Tensor:
    """(1, L, 40, 40, 40) bool: the faces of a box that a camera looking along +z sees (front,
    left, top), moving one voxel along x a view."""
    grids = torch.zeros(1, views, 40, 40, 40, dtype=torch.bool)
    for t in range(views):
        i0, i1 = 12 + t, 28 + t
        grids[0, t, i0:i1, 14:26, 12] = True
        grids[0, t, i0, 14:26, 12:24] = True
        grids[0, t, i0:i1, 14, 12:24] = True
    return grids


def test_every_shipped_model_is_there() -> None:
    assert sorted(p.stem for p in WEIGHTS_DIR.glob("*.pt")) == sorted(SHIPPED)
    size = sum(p.stat().st_size for p in WEIGHTS_DIR.iterdir() if p.is_file())
    assert size < 40 * 2**20  # all of completion/weights/ under 40 MB


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_checkpoint_is_its_default_architecture(name: str) -> None:
    stored = ModelConfig.from_dict(read_checkpoint(WEIGHTS_DIR / f"{name}.pt")["config"])
    assert stored == DEFAULT_CONFIGS[name].replace(seed=stored.seed)
    # a training run of --model X with no other option builds exactly that architecture
    args = parse_args(["--model", name, "--out", "unused.pt", "--seed", str(stored.seed)])
    assert run_config(args) == stored


@pytest.mark.parametrize("name", SHIPPED)
@torch.no_grad()
def test_shipped_weights_give_the_pinned_logits(name: str) -> None:
    torch.set_num_threads(1)
    model = load_model(name)
    x = box_views()
    # the posed model is also given what earlier views saw: the views before, as one surface
    seen = None if name != "mvp_posed" else torch.cumsum(x, 1).roll(1, 1).clamp(max=1)
    if seen is not None:
        seen[:, 0] = 0
    parallel = model(x) if seen is None else model(x, seen=seen)
    mean, centre, behind = PINNED[name]
    assert parallel.double().mean().item() == pytest.approx(mean, abs=2e-5)
    got = [parallel[0, t, 20, 20, 18].item() for t in range(3)]
    assert got == pytest.approx(centre, abs=2e-5)
    assert parallel[0, 2, 20, 20, 30].item() == pytest.approx(behind, abs=2e-5)
    state, streamed = model.init_state(1), []
    for t in range(x.shape[1]):
        logits, state = (model.step(state, x[:, t]) if seen is None
                         else model.step(state, x[:, t], seen=seen[:, t]))
        streamed.append(logits)
    torch.testing.assert_close(torch.stack(streamed, 1), parallel, atol=1e-4, rtol=0)
    assert model.threshold == pytest.approx(0.5)  # the threshold shipped for all seven


def recipe_commands() -> list[list[str]]:
    """The recipe's commands, as it would run them (``DRY_RUN=1`` prints instead of running)."""
    out = subprocess.run(["bash", str(RECIPE)], env={**os.environ, "DRY_RUN": "1"},
                         capture_output=True, text=True, check=True).stdout
    return [shlex.split(line) for line in out.splitlines() if line.strip()]


def test_the_recipe_parses_and_ends_with_the_shipped_seven() -> None:
    commands = recipe_commands()
    trains = [c[3:] for c in commands if c[:3] == ["python", "-m", "completion.train"]
              and c[3] not in ("select-threshold", "model-card")]
    assert len(trains) >= 20
    outs = []
    for argv in trains:
        args = parse_args(argv)  # every option exists and passes the command's checks
        run_config(args)
        outs.append(args.out)
    # stage 11 writes the six paper models (an earlier one shipped its own six before) and one
    # threshold is chosen for all; stage 12 trains and ships the posed model last
    copies = [c for c in commands if c[0] == "cp" and c[2].startswith("completion/weights/")]
    shipped = copies[-7:-1]
    assert sorted(Path(c[2]).stem for c in shipped) == sorted(SIX)
    assert {Path(o) for o in outs[-7:-1]} == {Path(c[1]) for c in shipped}
    assert Path(copies[-1][2]).stem == "mvp_posed" and Path(outs[-1]) == Path(copies[-1][1])
    assert any(c[:4] == ["python", "-m", "completion.train", "select-threshold"]
               for c in commands)
    generated = [c for c in commands if c[:4] == ["python", "-m", "completion.data", "generate"]]
    assert generated, "the recipe makes its own data"
