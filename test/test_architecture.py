"""The package's layering, read from the source: no import cycle, no ROS under core/.

No module is imported: every ``import`` / ``from ... import`` statement of a module, at
module level or inside a function (a lazy import is a dependency too), becomes an edge to
the deepest scanned module that it names. Cycles are the strongly connected components of
more than one module.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path
from typing import Iterable

def _modules(root: Path, packages: Iterable[str]) -> dict[str, tuple[Path, bool]]:
    mods: dict[str, tuple[Path, bool]] = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            is_pkg = parts[-1] == "__init__"
            if is_pkg:
                parts = parts[:-1]
            mods[".".join(parts)] = (path, is_pkg)
    return mods


def _absolute(name: str, current: str, is_pkg: bool, level: int) -> str:
    if level == 0:
        return name
    base = current.split(".")
    if not is_pkg:
        base = base[:-1]
    if level > 1:
        base = base[: len(base) - (level - 1)]
    return ".".join(base + ([name] if name else []))


def _imported_names(path: Path, module: str, is_pkg: bool) -> list[str]:
    names: list[str] = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            names.extend(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(node.module or "", module, is_pkg, node.level)
            names.append(base)
            names.extend(f"{base}.{a.name}" for a in node.names)
    return names


def import_graph(root: Path, packages: Iterable[str]) -> dict[str, set[str]]:
    """module -> the modules of ``packages`` (under ``root``) that it imports."""
    mods = _modules(Path(root), packages)
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, (path, is_pkg) in mods.items():
        for name in _imported_names(path, mod, is_pkg):
            while name and name not in mods:
                name = name.rpartition(".")[0]
            if name and name != mod:
                graph[mod].add(name)
    return graph


def external_imports(root: Path, package: str) -> dict[str, set[str]]:
    """module of ``package`` -> the top-level names of everything it imports."""
    out: dict[str, set[str]] = {}
    for mod, (path, is_pkg) in _modules(Path(root), [package]).items():
        out[mod] = {n.split(".")[0] for n in _imported_names(path, mod, is_pkg) if n}
    return out


def import_cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph) + 100))

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return sorted(found)


ROOT = Path(__file__).resolve().parents[1]
PACKAGES = [p.name for p in ROOT.iterdir() if p.is_dir() and (p / "__init__.py").is_file()
            and p.name == "soma_ros"]
ROS_NAMES = {"rclpy", "rosidl_runtime_py", "sensor_msgs", "std_msgs", "geometry_msgs", "tf2_msgs",
             "builtin_interfaces", "std_srvs", "soma_msgs"}


def test_the_detector_finds_a_cycle_held_by_a_lazy_import(tmp_path):
    pkg = tmp_path / "pkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .b import f\n")
    (pkg / "b.py").write_text("def f():\n    from . import a\n")
    (pkg / "c.py").write_text("from pkg.a import f\n")
    assert import_cycles(import_graph(tmp_path, ["pkg"])) == [["pkg.a", "pkg.b"]]


def test_no_import_cycle():
    cycles = import_cycles(import_graph(ROOT, PACKAGES))
    assert cycles == [], "import cycles: " + "; ".join(" <-> ".join(c) for c in cycles)


def test_core_imports_no_ros():
    found = {mod: sorted(names & ROS_NAMES) for mod, names in external_imports(ROOT, "soma_ros").items()
             if mod.startswith("soma_ros.core") and names & ROS_NAMES}
    assert found == {}, f"ROS imports under soma_ros/core: {found}"


#: The package's layers, lowest first: a module may import its own layer and those below.
LAYERS = [
    {"core"},
    {"world", "data", "scene"},
    {"training"},
    {"evaluation"},
    {"discrepancy"},
    {"live", "live_render", "nodes", "viewer", "commands", "cli", "demo", "demo_report"},
]
#: Modules of the package root that sit below every layer (no soma_ros imports of their own).
FOUNDATION = {"soma_ros", "soma_ros.paths", "soma_ros.bagtypes"}


def _layer(module: str) -> int:
    area = module.split(".")[1] if module.count(".") >= 1 else ""
    for rank, names in enumerate(LAYERS):
        if area in names:
            return rank
    raise AssertionError(f"{module}: not in any layer of test_architecture.LAYERS")


def test_imports_point_down_the_layers():
    graph = import_graph(ROOT, ["soma_ros"])
    upward = sorted(f"{m} -> {t}" for m, ts in graph.items() if m not in FOUNDATION
                    for t in ts if t not in FOUNDATION and _layer(t) > _layer(m))
    assert upward == [], "imports that point up the layers:\n" + "\n".join(upward)


def test_the_foundation_imports_nothing_above_it():
    graph = import_graph(ROOT, ["soma_ros"])
    bad = sorted(f"{m} -> {t}" for m in FOUNDATION for t in graph.get(m, ()) if t not in FOUNDATION)
    assert bad == []
