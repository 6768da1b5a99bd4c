"""The code's imports agree with the layers docs/ARCHITECTURE.md draws: no upward import, no import
between peers of one layer, no cycle between modules, and no project module imported inside a function
except where a measured reason is written here. Parsed with `ast`, so nothing is imported to check it."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("fuzzy", "core", "planning", "master", "agents", "farm", "quekaro", "bench")
# Function-level imports of project modules, each with its measured reason.
LAZY_PROJECT = {
    ("quekaro.cli", "agents.render_agent"): "SPADE takes ~0.6 s to import; only `quekaro agent` needs it",
    ("quekaro.cli", "fuzzy.errors"): "`fuzzy` loads its engine and numpy (~0.1 s), after `quekaro render` has "
                                     "started its render process (core.render.child), whose Mitsuba import overlaps",
    ("quekaro.cmd_farm", "master.run"): "SPADE and aiohttp take ~0.4 s; only `quekaro master` needs them",
    ("bench.cli", "bench.commands"): "matplotlib and pyfuzzylite (~0.3 s; pyfuzzylite sets up the root logger "
                                     "at import, which silenced every farm log): only `quekaro bench` loads them",
    ("planning.plain", "core.render.worker"): "the uniform baseline's process is timed as a user's plain render: "
                                              "the worker's modules (~60 ms) load only for an integrator or depth "
                                              "override",
}
# Third-party modules that may be imported inside functions (the comment at each says why).
LAZY_THIRD_PARTY = {"mitsuba", "drjit", "pyjabber", "loguru"}


def read_layers() -> list[list[str]]:
    """The layers block of ARCHITECTURE.md, lowest first: each layer a list of peer names."""
    text = (REPO / "docs" / "ARCHITECTURE.md").read_text()
    block = re.search(r"<!-- layers -->\s*```text\n(.*?)```\s*<!-- /layers -->", text, re.S)
    assert block, "docs/ARCHITECTURE.md has no layers block"
    rows = [re.split(r"\s{2,}", line.strip(), maxsplit=1)[0] for line in block.group(1).splitlines() if line.strip()]
    return [[name.strip() for name in row.split("|")] for row in reversed(rows)]


def modules() -> dict[str, ast.Module]:
    out = {}
    for package in PACKAGES:
        for path in sorted((REPO / package).rglob("*.py")):
            name = ".".join(path.relative_to(REPO).with_suffix("").parts).removesuffix(".__init__")
            out[name] = ast.parse(path.read_text(), str(path))
    return out


def imports(tree: ast.Module) -> list[tuple[str, bool, int]]:
    """(imported module, at module level?, line) for every import; `from a import b` counts as a.b
    when a.b is a module, else as a."""
    top = {id(node) for node in tree.body}
    top |= {id(n) for node in tree.body if isinstance(node, ast.If) for n in node.body}  # TYPE_CHECKING blocks
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found += [(alias.name, id(node) in top, node.lineno) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            found += [(f"{node.module}.{alias.name}", id(node) in top, node.lineno) for alias in node.names]
    return found


def resolve(name: str, known: set[str]) -> str | None:
    """The project module an import names (the longest known prefix), or None for other packages."""
    parts = name.split(".")
    for n in range(len(parts), 0, -1):
        if ".".join(parts[:n]) in known:
            return ".".join(parts[:n])
    return None


def layer_of(module: str, layers: list[list[str]]) -> tuple[int, str]:
    """(layer index, the layer entry naming it): the entry that is the longest prefix of the module."""
    best = max(((i, e) for i, row in enumerate(layers) for e in row if module == e or module.startswith(e + ".")),
               key=lambda ie: len(ie[1]), default=None)
    assert best is not None, f"module {module} is in no layer of docs/ARCHITECTURE.md"
    return best


@pytest.fixture(scope="module")
def graph() -> dict[str, list[tuple[str, bool, int]]]:
    trees = modules()
    known = set(trees)
    out = {}
    for name, tree in trees.items():
        out[name] = [(target, top, line) for imported, top, line in imports(tree)
                     if (target := resolve(imported, known)) is not None and target != name]
    return out


def test_the_document_names_every_package_once() -> None:
    names = [e for row in read_layers() for e in row]
    assert len(names) == len(set(names))
    assert set(PACKAGES) <= {n.split(".")[0] for n in names}


def test_every_import_goes_down_or_stays_in_its_own_entry(graph) -> None:
    layers = read_layers()
    bad = []
    for module, targets in graph.items():
        mine = layer_of(module, layers)
        for target, _, line in targets:
            theirs = layer_of(target, layers)
            if theirs[1] != mine[1] and theirs[0] >= mine[0]:
                bad.append(f"{module}:{line} imports {target} ({mine[1]} -> {theirs[1]})")
    assert not bad, "imports against docs/ARCHITECTURE.md's layers:\n" + "\n".join(bad)


def test_no_import_cycle_between_modules(graph) -> None:
    edges = {m: {t for t, _, _ in targets} for m, targets in graph.items()}
    cycles = [c for c in strongly_connected(edges) if len(c) > 1]
    assert not cycles, f"import cycles: {cycles}"


def test_project_imports_sit_at_module_top(graph) -> None:
    inner = {(m, t) for m, targets in graph.items() for t, top, _ in targets if not top}
    assert inner <= set(LAZY_PROJECT), f"imports inside functions without a reason: {sorted(inner - set(LAZY_PROJECT))}"


def test_third_party_imports_inside_functions_are_the_heavy_ones_only() -> None:
    known = set(modules())
    bad = [f"{name}:{line} {imported}" for name, tree in modules().items()
           for imported, top, line in imports(tree)
           if not top and resolve(imported, known) is None and imported.split(".")[0] not in LAZY_THIRD_PARTY]
    assert not bad, f"imports inside functions: {bad}"


def test_the_checker_sees_an_upward_import_and_a_cycle() -> None:
    layers = [["fuzzy"], ["core"], ["master", "agents"]]
    assert layer_of("core.render.scene", layers) == (1, "core")
    assert layer_of("agents.state", layers)[0] == layer_of("master.store", layers)[0] == 2
    assert [c for c in strongly_connected({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) if len(c) > 1] == \
        [["a", "b", "c"]]


def strongly_connected(edges: dict[str, set[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components, each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
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
            out.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out
