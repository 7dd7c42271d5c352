"""The layering of the code: no module of `salad` or `app` imports, directly or through others,
a module that imports it back. Imports inside functions count too, since hiding an import in a
function only postpones the circle; `if TYPE_CHECKING:` blocks do not, as they never run."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("salad", "app")


def module_name(path: Path, root: Path = REPO) -> str:
    parts = list(path.relative_to(root).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def project_modules() -> dict[str, Path]:
    return {module_name(p): p for pkg in PACKAGES for p in sorted((REPO / pkg).rglob("*.py"))}


def _imported_names(node: ast.Import | ast.ImportFrom, module: str, is_package: bool) -> list[str]:
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        here = module.split(".") if is_package else module.split(".")[:-1]
        here = here[: len(here) - (node.level - 1)]
        base = ".".join(here + ([base] if base else []))
    # `from a import b` runs a's __init__ and then b, which may be a module of its own
    return [base] + [f"{base}.{a.name}" for a in node.names]


def _is_type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the project modules it imports anywhere in its body (a name is mapped to the
    longest module prefix it has: `salad.motion.skeleton.JOINT_NAMES` -> salad.motion.skeleton)."""
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for module, path in modules.items():
        is_package = path.name == "__init__.py"
        stack = [ast.parse(path.read_text(encoding="utf-8"), filename=str(path))]
        while stack:
            for child in ast.iter_child_nodes(stack.pop()):
                if _is_type_checking(child):
                    continue
                if isinstance(child, (ast.Import, ast.ImportFrom)):
                    for name in _imported_names(child, module, is_package):
                        while name and name not in modules:
                            name = name.rpartition(".")[0]
                        if name and name != module:
                            graph[module].add(name)
                stack.append(child)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    found: list[list[str]] = []
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = len(index)
        stack.append(root)
        on_stack.add(root)
        while work:
            v, children = work[-1]
            w = next(children, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = len(index)
                    stack.append(w)
                    on_stack.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on_stack:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                component = []
                while True:
                    w = stack.pop()
                    on_stack.discard(w)
                    component.append(w)
                    if w == v:
                        break
                if len(component) > 1:
                    found.append(sorted(component))
    return found


def test_cycle_finder_sees_circles():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": {"e"}}
    assert cycles(graph) == [["a", "b", "c"]]


def test_graph_reads_function_level_and_skips_type_checking(tmp_path):
    root = tmp_path / "salad"
    (root / "sub").mkdir(parents=True)
    (root / "__init__.py").write_text("")
    (root / "sub" / "__init__.py").write_text("from .low import x\n")
    (root / "sub" / "low.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                         "    from ..top import y\ndef f():\n    from .. import top\n")
    (root / "top.py").write_text("from .sub.low import x\n")
    graph = import_graph({module_name(p, tmp_path): p for p in root.rglob("*.py")})
    assert graph["salad.sub.low"] == {"salad", "salad.top"}
    assert graph["salad.top"] == {"salad.sub.low"}
    assert cycles(graph) == [["salad.sub.low", "salad.top"]]


@pytest.mark.parametrize("package", PACKAGES)
def test_no_import_cycles(package):
    modules = project_modules()
    found = [c for c in cycles(import_graph(modules)) if any(m.split(".")[0] == package for m in c)]
    assert not found, "import circles (each line: modules that import one another):\n" + "\n".join(
        "  " + " <-> ".join(c) for c in found)
