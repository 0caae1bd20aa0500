"""Every Python snippet in the README runs as written (the service one against a real server)."""

from __future__ import annotations

import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

ROOT = Path(__file__).resolve().parents[1]
SNIPPETS = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(), re.S)
SERVICE_URL = "http://127.0.0.1:8000"


def test_the_readme_has_python_snippets():
    assert len(SNIPPETS) >= 3


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """``python -m service`` on the README's port with the shipped MVP, a throwaway store."""
    with socket.socket() as s:
        if s.connect_ex(("127.0.0.1", 8000)) == 0:
            pytest.fail("port 8000 is taken; the README's service snippet needs it")
    store = tmp_path_factory.mktemp("store") / "s.sqlite"
    env = os.environ | {"GRASP_STORE_PATH": str(store)}
    proc = subprocess.Popen([sys.executable, "-m", "service", "--port", "8000"], cwd=ROOT,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            try:
                if httpx.get(f"{SERVICE_URL}/healthz", timeout=2).status_code == 200:
                    break
            except httpx.TransportError:
                time.sleep(0.5)
            assert proc.poll() is None, proc.stderr.read().decode()
        else:
            pytest.fail("the service did not come up within 120 s")
        yield SERVICE_URL
    finally:
        proc.terminate()
        proc.wait(timeout=30)


@pytest.mark.parametrize("index", range(len(SNIPPETS)))
def test_readme_snippet_runs(index, request, capsys):
    code = SNIPPETS[index]
    if SERVICE_URL in code:
        request.getfixturevalue("server")
    exec(compile(code, f"README.md snippet {index}", "exec"), {"__name__": "__readme__"})
