"""The project's modules import each other without cycles and only downwards (lazy, in-function imports
included): client -> server -> engine (ogmapping) -> render, with the API package (ogapi) below the
client and the server and independent of the engine. The client never imports the server: it reaches
one over gRPC, or starts one as a child process through the server's command line (``ogclient view``,
``make demo``)."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# Package name -> the folder that holds it (see [tool.setuptools.packages.find] in pyproject.toml).
ROOTS = {"ogmapping": REPO, "ogapi": REPO / "proto", "ogserver": REPO / "server", "ogclient": REPO / "client"}


def project_modules() -> dict[str, Path]:
    modules = {}
    for package, root in ROOTS.items():
        for path in (root / package).rglob("*.py"):
            parts = path.relative_to(root).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            modules[name] = path
    return modules


def imported(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Project modules ``name`` imports anywhere in its source (``from a import b``: a.b when
    that is a module, else a)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    targets = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            targets.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.rsplit(".", node.level - 1)[0] if node.level > 1 else package
                base = f"{anchor}.{base}" if base else anchor
            for alias in node.names:
                targets.add(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base)
    return {target for target in targets if target in modules and target != name}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for successor in sorted(graph[node]):
            if successor not in index:
                visit(successor)
                low[node] = min(low[node], low[successor])
            elif successor in on_stack:
                low[node] = min(low[node], index[successor])
        if low[node] == index[node]:
            component = []
            while True:
                member = stack.pop()
                on_stack.discard(member)
                component.append(member)
                if member == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def import_graph() -> dict[str, set[str]]:
    modules = project_modules()
    return {name: imported(name, path, modules) for name, path in modules.items()}


def test_no_module_imports_another_in_a_cycle() -> None:
    graph = import_graph()
    assert len(graph) > 60, "the scan found the project's modules"
    assert cycles(graph) == []


def test_the_cycle_finder_finds_cycles() -> None:
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(graph) == [["a", "b", "c"]]


def may_import(importer: str, imported: str) -> bool:
    """The layering: ogapi stands alone; the engine knows neither the API, the server nor the client;
    the server no client, the client no server; render only itself and the engine's leaf modules it shares."""
    package = imported.split(".")[0]
    if importer.startswith("ogapi"):
        return package == "ogapi"
    if importer.startswith("ogmapping.render"):
        return imported.startswith("ogmapping.render") or imported in RENDER_MAY_USE
    if importer.startswith("ogmapping"):
        return package == "ogmapping"
    if importer.startswith("ogserver"):
        return package != "ogclient"
    if importer.startswith("ogclient"):
        return package != "ogserver"
    return True


# Leaf modules of the engine (no project imports of their own) that the render backends share.
RENDER_MAY_USE = {"ogmapping.backends", "ogmapping.arrays", "ogmapping.frames.rotation"}


def test_imports_flow_one_way() -> None:
    graph = import_graph()
    upward = sorted(f"{importer} -> {target}" for importer, targets in graph.items() for target in targets
                    if not may_import(importer, target))
    assert upward == []
    assert all(not graph[leaf] for leaf in RENDER_MAY_USE), "render's shared engine modules stay leaves"


def test_a_lazy_import_of_the_server_in_the_client_is_refused(tmp_path) -> None:
    source = tmp_path / "viewing.py"
    source.write_text("def view():\n    from ogserver.web import still\n    import ogserver.view\n")
    found = imported("ogclient.viewing", source, project_modules())
    assert found == {"ogserver.web.still", "ogserver.view"}
    assert not any(may_import("ogclient.viewing", target) for target in found)


def stage_of(module: str) -> str:
    """The engine's stage a module belongs to: its subpackage of ogmapping (``ogmapping.optim``), or
    the module itself when it sits at the top level."""
    parts = module.split(".")
    return ".".join(parts[:2])


def test_the_engine_stages_import_each_other_without_cycles() -> None:
    """The subpackages of ogmapping (frames, structure, model, optim, persist, quality, runtime, render,
    datasets) stay layered: collapsed to one node each, no group imports one that imports it back."""
    graph: dict[str, set[str]] = {}
    for importer, targets in import_graph().items():
        if importer.startswith("ogmapping."):
            stage = stage_of(importer)
            graph.setdefault(stage, set()).update(
                stage_of(target) for target in targets if target.startswith("ogmapping.") and stage_of(target) != stage)
    assert {"ogmapping.frames", "ogmapping.structure", "ogmapping.model", "ogmapping.optim"} <= graph.keys()
    assert cycles(graph) == []
