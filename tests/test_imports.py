"""Imports run one way: no load-time cycles between fbgforce modules, no cycles between its
subpackages, and each layer imports only the layers below it, counting imports inside
functions (units and the contract at the bottom, the runtime binding above them, the exporter
and trainer above that, commands and tools on top; benchmarks import no tests)."""
from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE_DIR = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["package-dir"]


def _modules() -> dict[str, Path]:
    out = {}
    for pkg, directory in PACKAGE_DIR.items():
        base = ROOT / directory
        for path in base.rglob("*.py"):
            rel = path.relative_to(base).with_suffix("")
            parts = [p for p in rel.parts if p != "__init__"]
            name = ".".join([pkg, *parts])
            if name in out or any(part.startswith(".") for part in rel.parts):
                continue
            out[name] = path
    return out


def _imported(node: ast.AST, known: set[str]) -> set[str]:
    """The fbgforce modules one statement imports (none for any other statement)."""
    if isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name.startswith("fbgforce")}
    if isinstance(node, ast.ImportFrom) and node.module and node.level == 0 \
            and node.module.startswith("fbgforce"):
        return {node.module} | {f"{node.module}.{a.name}" for a in node.names
                                if f"{node.module}.{a.name}" in known}
    return set()


def _imports(path: Path, name: str, known: set[str], *, deferred: bool = False) -> set[str]:
    """fbgforce modules imported by one module: at module level only (the imports that make a
    load-time cycle), or with ``deferred`` also those inside functions (an import deferred for
    start-up time or an optional dependency is still a dependency, and runs one way too)."""
    tree = ast.parse(path.read_text())
    found: set[str] = set()

    def visit(nodes: list[ast.stmt]) -> None:
        for node in nodes:
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            found.update(_imported(node, known))
            for field in ("body", "orelse", "finalbody", "handlers"):
                inner = getattr(node, field, None)
                if isinstance(inner, list) and not isinstance(node, ast.ClassDef):
                    visit([n for n in inner if isinstance(n, ast.stmt)])
                elif isinstance(node, ast.ClassDef) and field == "body":
                    visit(node.body)

    if deferred:
        for node in ast.walk(tree):
            found.update(_imported(node, known))
    else:
        visit(tree.body)
    return {m for m in found if m in known and m != name}


def _graph(*, deferred: bool = False) -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    return {name: _imports(path, name, known, deferred=deferred) for name, path in mods.items()}


def test_no_import_cycles():
    graph = _graph(deferred=True)
    state: dict[str, int] = {}
    stack: list[str] = []

    def dfs(node: str) -> None:
        state[node] = 1
        stack.append(node)
        for dep in sorted(graph.get(node, ())):
            if dep.startswith(node + "."):
                continue          # a package importing its own submodule
            if state.get(dep) == 1:
                cycle = stack[stack.index(dep):] + [dep]
                raise AssertionError("import cycle: " + " -> ".join(cycle))
            if dep not in state:
                dfs(dep)
        stack.pop()
        state[node] = 2

    for node in sorted(graph):
        if node not in state:
            dfs(node)


# Layer of each module (prefix match, longest first); a module may import its own layer and
# the layers below it.
LAYERS = {
    # base modules
    "fbgforce.contract": 0, "fbgforce.units": 0, "fbgforce.errors": 0, "fbgforce.jsonutil": 0,
    "fbgforce.fileio": 0, "fbgforce.signals": 0, "fbgforce.samples": 0, "fbgforce.progress": 0,
    "fbgforce.cliargs": 0,
    # the core: recordings, the model, the metrics and figures; the compiled runtime
    "fbgforce.geometry": 1, "fbgforce.recordings": 1, "fbgforce.model": 1, "fbgforce.evaluation": 1,
    "fbgforce._runtime": 1,
    "fbgforce.pybind": 2,
    "fbgforce.export": 3, "fbgforce.trainer": 3, "fbgforce.sim": 3, "fbgforce.interrogator": 3,
    # every engine by name: above the exporter and the runtime binding whose engines it runs
    "fbgforce.evaluation.engines": 4,
    "fbgforce.trainer.evaluate": 5, "fbgforce.trainer.report": 5,
}


def _layer(name: str) -> int:
    if name.rsplit(".", 1)[-1] == "cli":
        return 9                              # command modules sit on top, whatever package
    best = None
    for prefix, layer in LAYERS.items():
        if (name == prefix or name.startswith(prefix + ".")) and (best is None or len(prefix) > len(best[0])):
            best = (prefix, layer)
    return 9 if best is None else best[1]     # commands, tools, benchmarks: the top


def test_layers_import_downward_only():
    bad = []
    for name, deps in _graph(deferred=True).items():
        for dep in deps:
            if name == "fbgforce" or dep == "fbgforce":
                continue
            if _layer(dep) > _layer(name):
                bad.append(f"{name} (layer {_layer(name)}) imports {dep} (layer {_layer(dep)})")
    assert not bad, "\n".join(sorted(bad))


SUBPACKAGES = ("export", "pybind", "trainer", "tradeoff", "sim", "teleop", "bench", "interrogator",
               "target", "scenes", "_runtime", "evaluation")


def subpackage(name: str) -> str:
    """The part of the house a module belongs to: a subpackage (``export``, ``pybind``, ...),
    ``commands`` (every ``cli``/``__main__`` module and the top-level commands of the core
    package, which sit above everything) or ``core`` (the rest of ``fbgforce``)."""
    parts = name.split(".")
    if parts[-1] in ("cli", "__main__") or (len(parts) > 1 and parts[1] not in SUBPACKAGES
                                             and _layer(name) == 9):
        return "commands"
    return parts[1] if len(parts) > 1 and parts[1] in SUBPACKAGES else "core"


def subpackage_graph() -> dict[str, set[str]]:
    """Which part imports which (:func:`subpackage`), counting imports inside functions."""
    out: dict[str, set[str]] = {}
    for name, deps in _graph(deferred=True).items():
        if name == "fbgforce":
            continue                          # the package's lazy public API re-exports all
        for dep in deps:
            a, b = subpackage(name), subpackage(dep)
            if a != b and dep != "fbgforce":
                out.setdefault(a, set()).add(b)
    return out


def test_no_cycles_between_subpackages():
    graph = subpackage_graph()
    done: set[str] = set()

    def visit(node: str, path: list[str]) -> None:
        if node in path:
            raise AssertionError("subpackages import each other: "
                                 + " -> ".join(path[path.index(node):] + [node]))
        if node in done:
            return
        for dep in sorted(graph.get(node, ())):
            visit(dep, path + [node])
        done.add(node)

    for node in sorted(graph):
        visit(node, [])
    assert graph["pybind"] == {"core"}


def test_benchmarks_do_not_import_tests():
    for path in (ROOT / "bench").glob("*.py"):
        text = path.read_text()
        assert "tests/" not in text.replace("python tests/", "") or "sys.path" not in text, path
        tree = ast.parse(text)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.module:
                assert not node.module.startswith(("tests", "conftest", "foreign")), (path, node.module)
            if isinstance(node, ast.Import):
                assert not any(a.name.startswith(("tests", "conftest", "foreign")) for a in node.names), path
