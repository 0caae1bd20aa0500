"""The client as a robot's computer gets it: ``clients/python`` installed alone in fresh virtual
environments on Python 3.10, 3.11 and 3.12, with numpy 1.26 (ROS 2 Humble and Jazzy) or 2.x, runs
its shipped example and its README's against a real server started from the main install and gets
a typed grasp; nothing of the server's (torch, pybullet, fcl, scipy, fastapi, pydantic, Pillow)
comes with it."""

from __future__ import annotations

import glob
import json
import re
import shutil
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from service_helpers import Server

REPO = Path(__file__).resolve().parents[1]
CLIENT = REPO / "clients" / "python"
#: (Python, numpy requirement): the ROS 2 numpy on the oldest and this project's Python, 2.x on
#: the newest.
MATRIX = (("3.10", "numpy<2"), ("3.11", "numpy<2"), ("3.12", "numpy>=2"))
#: What a robot PC must not get with the client.
SERVER_ONLY = {"torch", "pybullet", "python-fcl", "scipy", "fastapi", "pydantic", "pillow",
               "trimesh", "uvicorn"}


def interpreter(version: str) -> str:
    """python3.X from PATH or pyenv's versions (these machines have 3.10 and 3.12 there)."""
    found = shutil.which(f"python{version}")
    if found and subprocess.run([found, "--version"], capture_output=True).returncode == 0:
        return found
    candidates = sorted(glob.glob(str(Path.home() / f".pyenv/versions/{version}.*/bin/python"
                                                  f"{version}")))
    assert candidates, f"Python {version} is needed for the client's tests (pyenv install)"
    return candidates[-1]


def make_venv(root: Path, version: str, numpy: str) -> Path:
    venv = root / f"py{version}"
    subprocess.run([interpreter(version), "-m", "venv", str(venv)], check=True)
    source = root / f"client-source-{version}"  # a copy: the build writes egg-info beside it
    shutil.copytree(CLIENT, source, ignore=shutil.ignore_patterns("*.egg-info", "__pycache__"))
    pip = [str(venv / "bin" / "python"), "-m", "pip", "install", "-q"]
    done = subprocess.run([*pip, numpy, str(source)], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    return venv


@pytest.fixture(scope="module")
def venvs(tmp_path_factory):
    root = tmp_path_factory.mktemp("client-venvs")
    with ThreadPoolExecutor(len(MATRIX)) as pool:  # pip waits on the network and disk mostly
        made = list(pool.map(lambda m: make_venv(root, *m), MATRIX))
    return dict(zip([m[0] for m in MATRIX], made, strict=True))


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("client-install")
    s = Server(tmp, str(REPO / "completion" / "weights" / "mvp.pt"), tmp / "store.sqlite",
               n_candidates=64, max_candidates=64)  # the service's default
    yield s
    s.stop()


@pytest.mark.slow
@pytest.mark.parametrize("version, numpy", MATRIX)
def test_the_client_alone_gets_a_typed_grasp_from_a_real_server(venvs, server, version, numpy):
    python = str(venvs[version] / "bin" / "python")
    listed = subprocess.run([python, "-m", "pip", "list", "--format=json"], capture_output=True,
                            text=True, check=True)
    installed = {p["name"].lower(): p["version"] for p in json.loads(listed.stdout)}
    print(f"Python {version}: numpy {installed['numpy']}, httpx {installed['httpx']}")
    assert not SERVER_ONLY & set(installed), installed
    assert installed["numpy"].startswith("1.26" if numpy == "numpy<2" else "2.")
    example = CLIENT / "examples" / "grasp_from_file.py"
    run = subprocess.run([python, str(example), "--url", server.url, "--min-hold", "0"],
                         capture_output=True, text=True, timeout=300,
                         cwd=venvs[version])  # not the checkout
    assert run.returncode == 0, run.stdout + run.stderr
    assert "pre-grasp pose (palm→world)" in run.stdout and "f3_dist" in run.stdout, run.stdout
    readme = re.findall(r"```python\n(.*?)```", (CLIENT / "README.md").read_text(), re.S)[0]
    run = subprocess.run([python, "-c", readme.replace("http://127.0.0.1:8000", server.url)],
                         capture_output=True, text=True, timeout=300, cwd=REPO)
    assert run.returncode == 0 and "[[" in run.stdout, run.stdout + run.stderr  # its example
    typed = subprocess.run(
        [python, "-c", "import sys, grasp_client, grasp_client.wire as w; "
         "heavy = {'torch', 'scipy', 'pydantic', 'PIL', 'fastapi'} & set(sys.modules); "
         "assert not heavy, heavy; print(w.Grasp.__module__)"],
        capture_output=True, text=True, cwd=venvs[version])
    assert typed.stdout.strip() == "grasp_client.wire", typed.stderr


def test_the_main_install_carries_the_same_client():
    """The service's own install imports the client from this checkout (one copy of the code)."""
    import grasp_client

    assert Path(grasp_client.__file__).resolve().parent == CLIENT / "grasp_client"
    assert sys.modules["grasp_client"] is grasp_client
