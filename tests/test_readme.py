"""Every Python snippet in the README and in docs/ runs as written (the service ones against a real
server), and every relative link in them points at a file that exists."""

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
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
         ROOT / "completion" / "weights" / "README.md", ROOT / "hands" / "barrett" / "README.md"]
SNIPPETS = [(page, code) for page in PAGES
            for code in re.findall(r"```python\n(.*?)```", page.read_text(), re.S)]
SERVICE_URL = "http://127.0.0.1:8000"
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def test_the_readme_has_python_snippets():
    readme = [code for page, code in SNIPPETS if page.name == "README.md" and page.parent == ROOT]
    assert len(readme) >= 2 and len(SNIPPETS) >= 4


def test_the_readme_reads_in_five_minutes():
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 250
    for page in PAGES:
        if page.name == "results.md":
            continue  # written by python -m grasp.evaluate: its tables do not wrap
        long = [i + 1 for i, line in enumerate(page.read_text().splitlines())
                if len(line) > 120 and not line.startswith("python3.11 -m venv")]  # one command
        assert not long, f"{page.relative_to(ROOT)}: lines over 120 characters: {long}"
    assert len((ROOT / "completion" / "weights" / "README.md").read_text().splitlines()) <= 250


@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_every_relative_link_points_at_a_file(page):
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)  # links, not code
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target) or target.startswith("#"):
            continue  # a web address or an anchor in the same page
        path = (page.parent / target.split("#")[0]).resolve()
        assert path.exists(), f"{page.relative_to(ROOT)} links to {target}, which is missing"


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


@pytest.mark.parametrize("index", range(len(SNIPPETS)),
                         ids=[f"{p.relative_to(ROOT)}-{i}" for i, (p, _) in enumerate(SNIPPETS)])
def test_snippet_runs(index, request, capsys, tmp_path, monkeypatch):
    page, code = SNIPPETS[index]
    if SERVICE_URL in code:
        request.getfixturevalue("server")
    monkeypatch.chdir(tmp_path)  # whatever a snippet writes lands outside the checkout
    exec(compile(code, f"{page.relative_to(ROOT)} snippet {index}", "exec"),
         {"__name__": "__readme__"})


@pytest.mark.parametrize("view", ["tabletop_view.npz", "clutter_view.npz"])
def test_the_client_example_says_what_it_got(server, view):
    """``clients/python/examples/grasp_from_file.py`` on each stored view: a grasp it may act on
    (exit 0), one under the hold probability the docs require (exit 3, warned), or none (exit 1,
    with the service's reason); the clutter view's label image makes obstacles."""
    examples = ROOT / "clients" / "python" / "examples"
    run = subprocess.run([sys.executable, str(examples / "grasp_from_file.py"), "--url", server,
                          "--view", str(examples / view)], capture_output=True, text=True,
                         timeout=300)
    out = run.stdout
    obstacles = int(re.search(r"(\d+) obstacle voxels kept clear of", out).group(1))
    assert (obstacles > 100) == (view == "clutter_view.npz"), out
    if run.returncode == 1:
        assert re.search(r"no grasp held: \S", out), out
        return
    hold = float(re.search(r"hold_probability=([0-9.]+)", out).group(1))
    assert "pre-grasp pose (palm→world)" in out and "f3_dist" in out, out
    assert run.returncode == (0 if hold >= 0.9 else 3), run.stdout + run.stderr
    assert ("warning: hold probability" in run.stderr) == (hold < 0.9), run.stderr


def test_ci_runs_the_readmes_test_command():
    readme = (ROOT / "README.md").read_text()
    command = re.findall(r"```bash\n(.*?)```", readme, re.S)[1].strip()  # the quick start's second
    assert command.endswith("pytest -q") and "\n" not in command
    install_and_test = command.split("&& ", 2)[2].replace("pip install -c", "pip install -q -c")
    assert install_and_test in (ROOT / ".ci" / "run").read_text()


def test_the_readme_layout_names_every_module():
    readme = (ROOT / "README.md").read_text()
    layout = readme[readme.index("## Layout"):]
    for package in ("completion", "grasp", "service", "hands", "clients/python/grasp_client"):
        for path in (ROOT / package).rglob("*.py"):
            if path.stem in ("__init__", "__main__"):
                continue
            named = path.name if path.parent.name in ("completion", "grasp", "service",
                                                      "grasp_client") \
                or path.parent.parent.name == "hands" else path.stem
            assert f"`{named}" in layout, f"README's layout does not name {path.relative_to(ROOT)}"


def test_the_service_page_lists_every_setting():
    from service.settings import Settings

    page = (ROOT / "docs" / "service.md").read_text()
    missing = [f"GRASP_{name.upper()}" for name in Settings.model_fields
               if f"GRASP_{name.upper()}" not in page]
    assert not missing, f"docs/service.md does not list {missing}"


def test_the_figures_in_the_readme_and_docs_are_those_of_docs_results():
    """A "± " figure in the README or docs/evaluation.md, and the grasp benchmark's rates in the
    README, are copied from docs/results.md (the default run's report): they cannot drift."""
    results = (ROOT / "docs" / "results.md").read_text().replace("−", "-")
    figure = re.compile(r"[+−-]?\d+\.\d+ ± \d+\.\d+")
    for page in (ROOT / "README.md", ROOT / "docs" / "evaluation.md"):
        for value in figure.findall(page.read_text()):
            assert value.replace("−", "-") in results, f"{page.name}: {value}"
    readme = " ".join((ROOT / "README.md").read_text().split())
    rates = re.search(r"holds (\d+) % planned on the true mesh, (\d+) % on MVP's completion of "
                      r"the 4 posed views \((\d+) % without their poses\), (\d+) % of 1 view, "
                      r"(\d+) % on registered fusion", readme)
    assert rates, "the README's benchmark sentence changed: update this test"
    labels = ("True mesh (planned on the truth)", "MVP, 4 views, camera poses used",
              "MVP, 4 views, poses not used (its memory alone)", "MVP, 1 view",
              "Registered fusion, 4 views (ref.)")
    for label, rate in zip(labels, rates.groups(), strict=True):
        assert f"| {label} | {rate}/100 |" in results, (label, rate)


def _table(text: str, title: str) -> dict[str, dict[str, str]]:
    """A results.md table under ``title``: row label -> column header -> cell, bold removed."""
    block = text.split(title, 1)[1].split("\n", 1)[1].strip().split("\n\n", 1)[0].splitlines()
    header = [c.strip() for c in block[0].strip("|").split("|")]
    rows = {}
    for line in block[2:]:
        cells = [c.strip().replace("**", "") for c in line.strip("|").split("|")]
        rows[cells[0]] = dict(zip(header[1:], cells[1:], strict=True))
    return rows


def test_the_readme_table_is_that_of_docs_results():
    results = (ROOT / "docs" / "results.md").read_text()
    jaccard = _table(results, "## Table I: Jaccard")
    joints = _table(results, "## Table III: grasp joint error")
    readme = (ROOT / "README.md").read_text().split("| model | camera pan |", 1)[1]
    rows = {"MVP": "MVP", "Single-View (same U-Net, no memory)": "Single-View",
            "MVP, memory off (each view alone)": "MVP, memory off: each view alone (ref.)",
            "prior (one fixed shape, ignores the input)": "Prior, ignores the input (ref.)"}
    columns = ["Camera Pan", "Object Hiding", "Object Reveal", "Slide Behind Other",
               "Two Object Pan", "Tabletop (ours)"]
    seen = 0
    for line in readme.splitlines()[2:]:
        if not line.startswith("|"):
            break
        cells = [c.strip() for c in line.strip("|").split("|")]
        if cells[0] not in rows:
            continue
        label, seen = rows[cells[0]], seen + 1
        for column, value in zip(columns, cells[1:7], strict=True):
            assert value == jaccard[label][f"{column} test"], (cells[0], column)
        assert cells[7] == joints[label]["Camera Pan test"].split(" ")[0], cells[0]
    assert seen == len(rows)

