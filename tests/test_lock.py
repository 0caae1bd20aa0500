"""Dependency ranges in pyproject.toml, the tested set in requirements.lock: every requirement is
pinned there within its range, this environment runs that set, the client's own ranges admit
it, and the service refuses a uvicorn its connection guards were not tested with."""

from __future__ import annotations

import re
import subprocess
import sys
import tomllib
from importlib import metadata
from pathlib import Path

import pytest
import uvicorn
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from packaging.version import Version

from service.server.connections import TESTED_UVICORN, check_uvicorn

ROOT = Path(__file__).resolve().parents[1]


def locked() -> dict[str, Version]:
    pins = re.findall(r"^([A-Za-z0-9_.\-]+)==(\S+)", (ROOT / "requirements.lock").read_text(), re.M)
    return {canonicalize_name(name): Version(version) for name, version in pins}


def requirements(pyproject: Path, *extras: str) -> list[Requirement]:
    project = tomllib.loads(pyproject.read_text())["project"]
    listed = project["dependencies"] + [r for e in extras
                                        for r in project["optional-dependencies"][e]]
    return [Requirement(r) for r in listed]


def test_every_requirement_is_locked_within_its_range():
    pins = locked()
    for req in requirements(ROOT / "pyproject.toml", "test", "cluster"):
        name = canonicalize_name(req.name)
        assert name in pins, f"{req.name} is not in requirements.lock: run pip-compile"
        assert req.specifier.contains(pins[name], prereleases=True), \
            f"requirements.lock pins {req.name}=={pins[name]}, outside {req.specifier}"
    for req in requirements(ROOT / "clients" / "python" / "pyproject.toml"):
        assert req.specifier.contains(pins[canonicalize_name(req.name)]), req


def test_this_environment_runs_the_locked_set():
    """What the tests run on is what the lock says (the README's install uses it)."""
    pins = locked()
    for req in requirements(ROOT / "pyproject.toml", "test", "cluster"):
        name = canonicalize_name(req.name)
        # the public version: torch's CPU build is 2.13.0+cpu where the lock pins 2.13.0
        assert Version(metadata.version(req.name)).public == pins[name].public, req.name


def test_the_service_refuses_an_untested_uvicorn():
    check_uvicorn(uvicorn.__version__)  # the installed one is tested
    assert ".".join(uvicorn.__version__.split(".")[:2]) in TESTED_UVICORN
    with pytest.raises(SystemExit, match=r"uvicorn 0\.99\.1 is installed.*tested with uvicorn"):
        check_uvicorn("0.99.1")
    started = subprocess.run(
        [sys.executable, "-c", "import uvicorn; uvicorn.__version__ = '0.99.1'; "
         "from service.__main__ import main; main(['--port', '0'])"],
        capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert started.returncode == 1 and "H11Protocol internals" in started.stderr, started.stderr
