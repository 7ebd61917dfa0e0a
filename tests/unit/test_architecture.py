"""The import graph, read from the source (no imports run): no circles, core at the bottom,
each layer importing only the layers under it (docs/architecture.md), and no test module
importing another test module (shared helpers live in tests/*support.py, the harness and
conftest)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
PACKAGES = ("cryptoros", "interceptor", "authz_server", "certs")
#: cryptoros's own sub-packages above the core, each its own layer
UPPER = ("cli", "lazy", "demo", "bench", "lab", "attack", "sim")
CORE = "cryptoros.core"
#: the asyncio ROS 1 node client (and the monitor's recorder and CLI, which run one): a
#: layer of its own above the sans-IO core, which has no event loop inside
NODE_CLIENT = "cryptoros.node_client"
NODE_CLIENT_MODULES = frozenset({"cryptoros.ros1.node", "cryptoros.ros1.topics", "cryptoros.ros1.services",
                                 "cryptoros.ros1.rpc", "cryptoros.ros1.master", "cryptoros.ros1.cli",
                                 "cryptoros.monitor.record", "cryptoros.monitor.cli"})
#: layer -> the layers it may import (besides itself)
ALLOWED = {
    CORE: set(),
    NODE_CLIENT: {CORE},
    "certs": {CORE},
    # policy from-graph asks a live master; the CLI's authoring verbs are imported on use
    "authz_server": {CORE, NODE_CLIENT, "cryptoros.lazy"},
    "interceptor": {CORE},  # a proxy, never a ROS node itself
    "cryptoros.sim": {CORE},
    "cryptoros.attack": {CORE, NODE_CLIENT, "cryptoros.sim"},
    "cryptoros.lazy": set(),
    "cryptoros.lab": {CORE, "certs"},
    "cryptoros.demo": {CORE, NODE_CLIENT, "cryptoros.lab", "cryptoros.sim", "cryptoros.attack", "interceptor"},
    "cryptoros.bench": {CORE, NODE_CLIENT, "cryptoros.lab", "cryptoros.sim", "cryptoros.lazy", "interceptor",
                        "certs"},
    "cryptoros.cli": {"cryptoros.lazy"},  # every subcommand is named by string and imported on use
}


def _modules() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in (REPO / package).rglob("*.py"):
            parts = path.relative_to(REPO).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            found[name] = path
    return found


def _imports(path: Path, known: dict[str, Path]) -> set[str]:
    """First-party modules ``path`` imports, at module level or inside functions."""

    def resolve(name: str) -> str | None:
        while name and name not in known:
            name = name.rpartition(".")[0]
        return name or None

    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(r for a in node.names if (r := resolve(a.name)))
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            for a in node.names:
                if r := resolve(f"{node.module}.{a.name}") or resolve(node.module):
                    out.add(r)
    return out


def _graph() -> dict[str, set[str]]:
    known = _modules()
    return {name: _imports(path, known) - {name} for name, path in known.items()}


def layer(module: str) -> str:
    if module in NODE_CLIENT_MODULES:
        return NODE_CLIENT
    parts = module.split(".")
    if parts[0] != "cryptoros":
        return parts[0]
    return f"cryptoros.{parts[1]}" if len(parts) > 1 and parts[1] in UPPER else CORE


def test_the_import_graph_has_no_circles():
    graph = _graph()
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []

    def visit(v: str) -> None:  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                circles.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    assert not circles, f"import circles: {circles}"


def test_each_layer_imports_only_the_layers_under_it():
    wrong = sorted(
        f"{a} -> {d}"
        for a, deps in _graph().items()
        for d in deps
        if layer(d) != layer(a) and layer(d) not in ALLOWED[layer(a)]
    )
    assert not wrong, "imports against the layering of docs/architecture.md:\n" + "\n".join(wrong)


def test_no_test_module_imports_another_test_module():
    offenders = []
    for path in sorted((REPO / "tests").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            offenders += [f"{path.name}: {n}" for n in names if n.startswith(("tests.test_", "tests.unit.", "tests.system."))]
    assert not offenders, offenders


def test_the_core_has_no_event_loop_inside():
    """Core modules are sans-IO or plain blocking helpers: none imports asyncio (the
    node client, the services and the tools above it do)."""
    offenders = []
    for name, path in _modules().items():
        if layer(name) != CORE:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            names = [a.name for a in node.names] if isinstance(node, ast.Import) else \
                [node.module] if isinstance(node, ast.ImportFrom) and node.module else []
            offenders += [f"{name}: {n}" for n in names if n == "asyncio" or n.startswith("asyncio.")]
    assert not offenders, offenders


def test_the_two_roles_do_not_import_each_other():
    graph = _graph()
    ros1 = {m for m in graph if m == "interceptor.ros1" or m.startswith("interceptor.ros1.")}
    ros2 = {"interceptor.ros2", "interceptor.ros2_bridge", "interceptor.ros2_partial"}
    assert ros1 and ros2 <= set(graph), (ros1, ros2)
    crossing = [f"{a} -> {d}" for a, deps in graph.items() for d in deps
                if (a in ros1 and d in ros2) or (a in ros2 and d in ros1)]
    assert not crossing, crossing
