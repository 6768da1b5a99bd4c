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
                                     "started its render process (core.render.spawn), whose Mitsuba import overlaps",
    ("quekaro.cmd_farm", "master.run"): "SPADE and aiohttp take ~0.4 s; only `quekaro master` needs them",
    ("quekaro.__main__", "quekaro.cli"): "in a try: Ctrl-C in the first ~0.1 s, while the command line imports, "
                                         "exits 130 without a traceback",
    ("bench.cli", "bench.commands"): "matplotlib and pyfuzzylite (~0.3 s; pyfuzzylite sets up the root logger "
                                     "at import, which silenced every farm log): only `quekaro bench` loads them",
    ("planning.plain", "core.render.process"): "the uniform baseline's process is timed as a user's plain render: "
                                              "the worker's modules (~60 ms) load only for an integrator or depth "
                                              "override",
}
# Third-party modules that may be imported inside functions (the comment at each says why).
LAZY_THIRD_PARTY = {"mitsuba", "drjit", "mitsuba_oidn"}  # OIDN: ~40 MB, denoised jobs only


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
    assert layer_of("core.scene.scene", layers) == (1, "core")
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


# ---- the auction's read API: nothing outside master/auction/ reads its internals ------------------------

AUCTION = "master.auction"
AUCTION_STATE = {"_jobs", "_agents", "_rounds"}  # its records, which only the machine touches


def auction_api() -> tuple[set[str], set[str]]:
    """(the package's exported names, the Auction's public members), read from their source."""
    init = ast.parse((REPO / "master" / "auction" / "__init__.py").read_text())
    exported = next(set(ast.literal_eval(node.value)) for node in init.body
                    if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "__all__")
    machine = ast.parse((REPO / "master" / "auction" / "machine.py").read_text())
    cls = next(n for n in machine.body if isinstance(n, ast.ClassDef) and n.name == "Auction")
    members = {n.name for n in cls.body if isinstance(n, ast.FunctionDef) and not n.name.startswith("_")}
    return exported, members | {"config"}


def internal_reads(name: str, tree: ast.Module, exported: set[str], members: set[str]) -> list[str]:
    """Where a module reads the auction other than through its exported names and the Auction's members."""
    bad, aliases = [], set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module:
            if node.module.startswith(AUCTION + "."):
                bad.append(f"{name}:{node.lineno} imports {node.module}")
            elif node.module == AUCTION:
                bad += [f"{name}:{node.lineno} imports {a.name}" for a in node.names if a.name not in exported]
            elif node.module == "master":
                aliases |= {a.asname or a.name for a in node.names if a.name == "auction"}
        elif isinstance(node, ast.Import):
            bad += [f"{name}:{node.lineno} imports {a.name}" for a in node.names if a.name.startswith(AUCTION + ".")]
    for node in ast.walk(tree):
        if not isinstance(node, ast.Attribute):
            continue
        base = node.value
        if node.attr in AUCTION_STATE:
            bad.append(f"{name}:{node.lineno} reads .{node.attr}")
        elif isinstance(base, ast.Name) and base.id in aliases and node.attr not in exported:
            bad.append(f"{name}:{node.lineno} reads {base.id}.{node.attr}")
        elif (getattr(base, "attr", None) == "auction" or getattr(base, "id", None) == "auction") \
                and node.attr not in members:
            bad.append(f"{name}:{node.lineno} reads auction.{node.attr}")
    return bad


def test_nothing_outside_the_auction_reads_its_internals() -> None:
    exported, members = auction_api()
    bad = [line for name, tree in modules().items() if not name.startswith(AUCTION)
           for line in internal_reads(name, tree, exported, members)]
    assert not bad, "reads of the auction past its read API (master/auction/__init__.py, Auction):\n" + "\n".join(bad)


def test_the_auction_checker_sees_a_read_of_its_internals() -> None:
    exported, members = auction_api()
    snippet = ast.parse("from master import auction as au\nfrom master.auction.state import UnitState\n"
                        "def f(service):\n    service.auction.jobs\n    au.Job\n    service.auction._agents\n"
                        "    service.auction.award_for('j', 0, 't')\n    au.Tick()\n")
    assert internal_reads("m", snippet, exported, members) == [
        "m:2 imports master.auction.state", "m:4 reads auction.jobs", "m:5 reads au.Job", "m:6 reads ._agents"]
