"""The layout docs/design.md §2 asks for: imports point one way, no two modules import each other
(not even through an import inside a function), and every file reads in one sitting."""

from __future__ import annotations

import ast
import graphlib
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("completion", "grasp", "service", "hands", "clients/python/grasp_client")
MAX_LINES = 600


def _modules() -> dict[str, Path]:
    out = {}
    for package in PACKAGES:
        root = (REPO / package).parent  # the folder the package is imported from
        for path in sorted((REPO / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            out[name] = path
    return out


def _imports(path: Path, name: str, known: set[str]) -> set[str]:
    """The project modules ``path`` imports anywhere in its body (top level, in functions,
    under TYPE_CHECKING), resolved to the deepest known module."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        targets: list[str] = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1]
                                + ([base] if base else []))
            targets = [f"{base}.{a.name}" for a in node.names] + [base]
        for target in targets:
            while target and target not in known:
                target = target.rpartition(".")[0]
            if target and target != name:
                found.add(target)
    return found


def _graph() -> dict[str, set[str]]:
    modules = _modules()
    known = set(modules)
    # a package's __init__ importing its own submodules is not a dependency of those submodules
    return {name: {t for t in _imports(path, name, known) if not name.startswith(t + ".")}
            for name, path in modules.items()}


def test_no_two_modules_import_each_other() -> None:
    graph = _graph()
    sorter = graphlib.TopologicalSorter(graph)
    try:
        sorter.prepare()
    except graphlib.CycleError as err:  # pragma: no cover - the failure message
        raise AssertionError(f"import cycle: {' -> '.join(err.args[1])}") from None


def test_imports_point_one_way() -> None:
    for name, targets in _graph().items():
        top = name.split(".")[0]
        for target in targets:
            assert not target.startswith("service") or top == "service", (name, target)
            if top == "grasp_client":  # installs alone on a robot: nothing of the project
                assert target.split(".")[0] == "grasp_client", (name, target)
            if top in ("completion", "hands"):  # the wire's types are shared, nothing else
                assert target.split(".")[0] == top or target == "grasp_client.wire", (name, target)


def test_every_source_and_test_file_reads_in_one_sitting() -> None:
    files = [p for package in (*PACKAGES, "tests") for p in (REPO / package).rglob("*.py")]
    long = {str(p.relative_to(REPO)): n for p in files
            if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"files over {MAX_LINES} lines: {long}"


#: The stages inside grasp/ and service/, lowest first (docs/design.md §2). A module belongs to
#: the group of its longest matching prefix; it may import its own group and the stages below,
#: never a stage above nor another group of its own stage (search and physics both build on the
#: hand and know nothing of each other).
STAGES = {
    "grasp": [
        ["grasp.defaults"],
        ["grasp.hand"],
        ["grasp.search", "grasp.physics"],
        ["grasp.ranking"],
        ["grasp.planner"],
        ["grasp.cli"],
        ["grasp.evaluate"],
        ["grasp.__main__"],
    ],
    "service": [
        ["service.api.schemas", "service.api.auth"],  # the wire's vocabulary; stdlib token checks
        ["service.intake"],
        ["service.settings"],  # builds the intake's limits and frame checks
        ["service.store"],
        ["service.engine"],
        ["service.services"],
        ["service.api"],
        ["service.app"],
        ["service.server", "service.load"],
        ["service.__main__"],
    ],
}


def _stage(name: str) -> tuple[int, str] | None:
    """(stage index, group) of a module of grasp/ or service/; None for the package itself."""
    best = None
    for i, stage in enumerate(STAGES.get(name.split(".")[0], [])):
        for group in stage:
            if (name == group or name.startswith(group + ".")) and (
                    best is None or len(group) > len(best[1])):
                best = (i, group)
    return best


def test_the_stages_import_downward_only() -> None:
    problems = []
    for name, targets in _graph().items():
        here = _stage(name)
        if here is None:
            continue
        for target in targets:
            there = _stage(target)
            if there is None or target.split(".")[0] != name.split(".")[0]:
                continue
            if there[0] > here[0] or (there[0] == here[0] and there[1] != here[1]):
                problems.append(f"{name} ({here[1]}) imports {target} ({there[1]})")
    assert not problems, "\n".join(problems)


def test_every_module_has_a_stage_and_the_top_levels_stay_small() -> None:
    """Every module of grasp/ and service/ sits in a stage; each package's top level holds at
    most six modules (the rest live in the stage folders)."""
    modules = [m for m in _modules() if m.split(".")[0] in STAGES]
    assert [m for m in modules if m not in STAGES and _stage(m) is None] == []
    for package in STAGES:
        top = sorted(p.name for p in (REPO / package).glob("*.py"))
        assert len(top) <= 6, (package, top)


def test_the_physics_check_imports_no_planner() -> None:
    assert not [(m, t) for m, targets in _graph().items() if m.startswith("grasp.physics")
                for t in targets
                if t.startswith(("grasp.planner", "grasp.search", "grasp.ranking"))]


#: Modules of grasp/ that hold constants only (they import nothing), which settings may name.
CONSTANTS = {"grasp.defaults"}


def test_the_service_settings_load_no_planner() -> None:
    """``service.settings`` (read by every process of the service, the client's tests, the docs)
    imports nothing of grasp/ beyond its constants modules, and those import nothing."""
    graph = _graph()
    assert {t for t in graph["service.settings"] if t.startswith("grasp")} <= CONSTANTS
    for name in CONSTANTS:
        assert not graph[name], (name, graph[name])


def test_the_wire_types_load_no_http_client() -> None:
    """The completion, the hand and the service share grasp_client's wire types: importing them
    does not import the client's httpx (it is imported when a client name is first used)."""
    import subprocess
    import sys

    code = ("import sys, completion.stream, completion.scenes, hands.barrett, "
            "service.intake.inputs; "
            "assert 'httpx' not in sys.modules, 'httpx loaded'; "
            "from grasp_client import GraspClient, SupportPlane; "
            "assert 'httpx' in sys.modules and GraspClient.__module__ == 'grasp_client.client'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=REPO)
