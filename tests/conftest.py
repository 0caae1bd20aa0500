"""Shared test settings: small thread counts so tests behave on a 2-core machine; a real Redis;
the fixtures of the service tests (their helpers are in tests/service_helpers.py)."""

import os
import shutil
import socket
import subprocess
import time

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")


#: The files that take a minute or more on the project's 2-core machine (``--durations``), run
#: first: pytest-xdist's ``--dist loadfile`` hands out files in collection order, so a long file
#: last would leave one worker running alone at the end.
SLOW_FILES = ("test_train.py", "test_evaluate.py", "test_cluster.py", "test_memory.py",
              "test_client_install.py", "test_objects.py")


def pytest_collection_modifyitems(config, items):
    first = {name: rank for rank, name in enumerate(SLOW_FILES)}
    items.sort(key=lambda item: first.get(item.path.name, len(first)))  # stable: order kept


def pytest_configure(config):
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # the grasp tests do not need torch
        pass


@pytest.fixture(scope="session")
def redis_url(tmp_path_factory):
    """A real ``redis-server`` (Debian's package; ``.ci/run`` installs it) on a free port."""
    server = shutil.which("redis-server")
    assert server, "redis-server is missing: apt-get install redis-server (.ci/run does)"
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    workdir = tmp_path_factory.mktemp("redis")
    process = subprocess.Popen(
        [server, "--port", str(port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no",
         "--dir", str(workdir)],
        stdout=subprocess.DEVNULL, stderr=subprocess.STDOUT,
    )  # fmt: skip
    deadline = time.monotonic() + 30
    while True:
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            assert process.poll() is None, "redis-server exited at start"
            assert time.monotonic() < deadline, "redis-server did not start in 30 s"
            time.sleep(0.05)
    yield f"redis://127.0.0.1:{port}/0"
    process.terminate()
    process.wait(timeout=30)


# ----------------------------------------------------------------------------- service fixtures
# Imported inside each fixture: the grasp tests run without torch.


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory) -> str:
    """A tiny untrained MVP checkpoint (path) standing in for the shipped weights."""
    from service_helpers import save_tiny

    return save_tiny(tmp_path_factory.mktemp("model") / "tiny.pt")


@pytest.fixture(scope="module")
def scene():
    """A simulated camera_pan scene (12 views) with depth images and masks."""
    from completion.scenes import make_sequence

    return make_sequence("camera_pan", "test", 0, seed=0, keep_depth=True)


@pytest.fixture
def client(tmp_path, tiny_model):
    """The app on ``tiny_model`` through FastAPI's TestClient (lifespan run)."""
    from fastapi.testclient import TestClient
    from service_helpers import settings

    from service.app import create_app

    with TestClient(create_app(settings(tmp_path, tiny_model))) as c:
        yield c
