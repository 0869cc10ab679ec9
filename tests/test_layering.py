"""Architecture rules, computed from the source of the whole package (efem_viz and annotator).

The import graph is read with `ast` from every module of the package: module-level and function-level imports,
relative imports resolved, imports under `if TYPE_CHECKING:` left out (they never run). The rules:

- **Direction**: every edge points down the layer order of `LAYERS` (ARCHITECTURE.md: base utilities → geometry →
  data → prior → em → eval → serve → {viewer, annotator, batch} → cli). A module may import its own layer
  and lower ones; sibling layers (viewer, annotator, batch) never import each other. CLI modules (`efem_viz.cli`,
  `*.commands`, `annotator.__main__`) sit on top of their own layer: only CLI modules import them (and their package's
  `__init__`, for a lazy re-export); every CLI module may use the dispatcher's helpers.
- **No cycles** between modules, function-level imports included: a lazy import hides a cycle, it does not remove it.
- **UI libraries**: viser only in `LAYERS.viser`; rich, tyro and tqdm never at import time in the core (geometry,
  data, prior, em, eval and the base utilities) outside CLI modules.
- **At run time**: every module imports; importing any module outside `LAYERS.viser` leaves viser unloaded; and
  `import efem_viz.cli` stays light.

Every failure names the offending edges as `a -> b (file:line)`. The checker itself is tested on a small synthetic
package (a back edge, a cycle, a hidden TYPE_CHECKING import), so that it cannot pass by finding nothing.
"""

from __future__ import annotations

import ast
import fnmatch
import json
import subprocess
import sys
from collections import deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import pytest

from efem_viz import cli

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("efem_viz", "annotator")
UI_LIBRARIES = ("rich", "tyro", "tqdm")
"""Terminal-UI libraries: only the CLI sets up rich/tqdm output (STYLE.md), so the core imports them lazily."""


@dataclass(frozen=True)
class Layers:
    """Where each module sits. Module patterns are exact names, `pkg.*` (the package and everything under it) or
    fnmatch patterns such as `*.commands`."""

    ranks: tuple[dict[str, tuple[str, ...]], ...]
    """Layer groups, lowest first; each maps a layer name to its module patterns. A module imports its own layer
    and lower groups; the layers of one group are siblings that do not import each other."""
    cli: tuple[str, ...]
    """CLI modules: they sit on top of their own layer and only CLI modules import them (or their package's
    `__init__`, for a lazy re-export)."""
    dispatcher: str
    """The CLI dispatcher: every CLI module may import its helpers, whatever its layer."""
    core: tuple[str, ...]
    """Layer names of the compute core: no `UI_LIBRARIES` import at import time outside CLI modules."""
    viser: tuple[str, ...]
    """The only module patterns that may import viser (at any level)."""

    def layer_of(self, module: str) -> tuple[int, str] | None:
        """The (rank, name) of the layer of `module`, by its longest matching pattern; None if no pattern matches."""
        best: tuple[int, int, str] | None = None
        for rank, group in enumerate(self.ranks):
            for name, patterns in group.items():
                for pattern in patterns:
                    if matches(module, pattern) and (best is None or len(pattern) > best[0]):
                        best = (len(pattern), rank, name)
        return None if best is None else (best[1], best[2])

    def is_cli(self, module: str) -> bool:
        """Whether `module` is a CLI module."""
        return any(matches(module, p) for p in self.cli)


LAYERS = Layers(
    ranks=(
        # base utilities, usable everywhere (the root package holds only __version__)
        {"base": ("efem_viz", "efem_viz._typeshims", "efem_viz.colors", "efem_viz.cpu", "efem_viz.terminal",
                  "efem_viz.typed")},
        {"geometry": ("efem_viz.geometry.*",)},
        {"data": ("efem_viz.data.*",)},
        {"prior": ("efem_viz.prior.*",)},
        {"em": ("efem_viz.em.*",)},
        {"eval": ("efem_viz.eval.*",)},
        # what both browser apps share about serving (access guard, client-value checks)
        {"serve": ("efem_viz.serve.*",)},
        {"viewer": ("efem_viz.viewer.*",), "annotator": ("annotator.*",), "batch": ("efem_viz.batch.*",)},
        {"cli": ("efem_viz.cli",)},
    ),
    cli=("efem_viz.cli", "*.commands", "annotator.__main__"),
    dispatcher="efem_viz.cli",
    core=("base", "geometry", "data", "prior", "em", "eval"),
    viser=("efem_viz.serve.*", "efem_viz.viewer.*", "annotator.app"),
)


def matches(module: str, pattern: str) -> bool:
    """Whether a dotted module name matches a `Layers` pattern (`pkg.*` also matches `pkg` itself)."""
    if pattern.endswith(".*"):
        return module == pattern[:-2] or module.startswith(pattern[:-1])
    return fnmatch.fnmatchcase(module, pattern)


class Edge(NamedTuple):
    """One import statement's edge: `src` imports `dst` at `file:line`."""

    src: str
    """Importing module (dotted)."""
    dst: str
    """Imported module: a module of the package, or the dotted name of a third-party one."""
    file: str
    """Source file of `src`, relative to the scanned root (posix)."""
    line: int
    """Line of the import statement."""
    at_import: bool
    """True when the statement runs when `src` is imported (not inside a function)."""

    def __str__(self) -> str:
        return f"{self.src} -> {self.dst} ({self.file}:{self.line})"


class ImportGraph(NamedTuple):
    """The import graph of a set of packages, read from their source."""

    modules: dict[str, Path]
    """Every module (dotted name → file); a package is named by its `__init__.py`."""
    internal: list[Edge]
    """Edges between modules of the packages."""
    external: list[Edge]
    """Edges to other modules (stdlib and third party); `dst` is the name as imported."""
    unresolved: list[Edge]
    """Imports of a module of the packages that does not exist."""


def find_modules(root: Path, packages: Sequence[str]) -> dict[str, Path]:
    """Every module of `packages` under `root` (folders without `__init__.py` are not packages and are skipped).

    Args:
        root: the folder that holds the packages.
        packages: top-level package names.

    Returns:
        Dotted module name → source file.
    """
    modules: dict[str, Path] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = path.relative_to(root).with_suffix("").parts
            if not all((root.joinpath(*parts[:i]) / "__init__.py").is_file() for i in range(1, len(parts))):
                continue
            modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return modules


def _is_type_checking(test: ast.expr) -> bool:
    """Whether an `if` test is `TYPE_CHECKING` or `typing.TYPE_CHECKING`."""
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


class _Import(NamedTuple):
    target: str
    """Absolute dotted module of the statement (`import a.b` → a.b; `from ..x import y` → the resolved x)."""
    names: tuple[str, ...]
    """Names of a `from` import (empty for `import`)."""
    line: int
    at_import: bool


class _ImportVisitor(ast.NodeVisitor):
    """Collects the import statements of one module, resolving relative ones; skips `if TYPE_CHECKING:` bodies."""

    def __init__(self, module: str, *, is_package: bool, type_checking: bool = False) -> None:
        self.type_checking = type_checking
        self.package = module.split(".") if is_package else module.split(".")[:-1]
        self.depth = 0
        self.found: list[_Import] = []

    def _function(self, node: ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda) -> None:
        self.depth += 1
        self.generic_visit(node)
        self.depth -= 1

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _function

    def visit_If(self, node: ast.If) -> None:
        if _is_type_checking(node.test) and not self.type_checking:
            for child in node.orelse:  # the `else:` branch does run
                self.visit(child)
            return
        self.generic_visit(node)

    def visit_Import(self, node: ast.Import) -> None:
        for alias in node.names:
            self.found.append(_Import(alias.name, (), node.lineno, self.depth == 0))

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level:
            keep = len(self.package) - (node.level - 1)
            base = self.package[:keep] if keep > 0 else []
            target = ".".join(base + ([node.module] if node.module else []))
        else:
            target = node.module or ""
        self.found.append(_Import(target, tuple(a.name for a in node.names), node.lineno, self.depth == 0))


def build_import_graph(root: Path, packages: Sequence[str], *, type_checking: bool = False) -> ImportGraph:
    """Read the import graph of `packages` (under `root`) from their source.

    `from pkg import name` is an edge to the submodule `pkg.name` when that module exists, else to `pkg`;
    `import a.b.c` is an edge to `a.b.c`. Imports under `if TYPE_CHECKING:` are left out.

    Args:
        root: the folder that holds the packages.
        packages: top-level package names; imports of any other top-level name are external.
        type_checking: also read the imports under `if TYPE_CHECKING:` (for the type-level cycle check).

    Returns:
        The graph, edges in file and line order.
    """
    modules = find_modules(root, packages)
    internal: list[Edge] = []
    external: list[Edge] = []
    unresolved: list[Edge] = []
    for module, path in modules.items():
        visitor = _ImportVisitor(module, is_package=path.name == "__init__.py", type_checking=type_checking)
        visitor.visit(ast.parse(path.read_text(encoding="utf-8"), filename=str(path)))
        file = path.relative_to(root).as_posix()
        for imp in visitor.found:
            if imp.target.split(".")[0] not in packages:
                external.append(Edge(module, imp.target, file, imp.line, imp.at_import))
                continue
            dsts = [f"{imp.target}.{n}" if f"{imp.target}.{n}" in modules else imp.target for n in imp.names]
            for dst in dict.fromkeys(dsts or [imp.target]):
                edge = Edge(module, dst, file, imp.line, imp.at_import)
                (internal if dst in modules else unresolved).append(edge)
    return ImportGraph(modules, internal, external, unresolved)


def _parent(module: str) -> str:
    return module.rpartition(".")[0]


def layering_violations(graph: ImportGraph, layers: Layers) -> list[str]:
    """Edges that break the layer rules of `layers` (see the module docstring), one line each.

    Args:
        graph: the import graph.
        layers: the layer table.

    Returns:
        `a -> b (file:line): why` for every offending edge, plus modules without a layer and imports of missing
        modules.
    """
    problems = [f"{m}: no layer (add it to LAYERS)" for m in graph.modules if layers.layer_of(m) is None]
    problems += [f"{e}: no such module" for e in graph.unresolved]
    for e in graph.internal:
        src, dst = layers.layer_of(e.src), layers.layer_of(e.dst)
        if src is None or dst is None:
            continue
        if layers.is_cli(e.dst) and not layers.is_cli(e.src) and e.src != _parent(e.dst):
            problems.append(f"{e}: only CLI modules import the CLI module {e.dst}")
        elif e.dst == layers.dispatcher or src[1] == dst[1] or dst[0] < src[0]:
            continue
        elif dst[0] == src[0]:
            problems.append(f"{e}: sibling layers {src[1]} and {dst[1]} do not import each other")
        else:
            problems.append(f"{e}: back edge, {src[1]} (layer {src[0]}) imports {dst[1]} (layer {dst[0]})")
    for e in graph.external:
        top = e.dst.split(".")[0]
        layer = layers.layer_of(e.src)
        if top == "viser" and not any(matches(e.src, p) for p in layers.viser):
            problems.append(f"{e}: viser is imported only in {', '.join(layers.viser)}")
        elif (top in UI_LIBRARIES and e.at_import and layer is not None and layer[1] in layers.core
              and not layers.is_cli(e.src)):
            problems.append(f"{e}: the core imports {top} only inside functions (or in a CLI module)")
    return problems


def _strongly_connected(nodes: Iterable[str], succ: dict[str, list[str]]) -> list[list[str]]:
    """Tarjan's strongly connected components (iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []
    for start in nodes:
        if start in index:
            continue
        work = [(start, iter(succ.get(start, [])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, it = work[-1]
            for nxt in it:
                if nxt not in index:
                    index[nxt] = low[nxt] = len(index)
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(succ.get(nxt, []))))
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component: list[str] = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    out.append(sorted(component))
    return out


def import_cycles(graph: ImportGraph) -> list[list[Edge]]:
    """Import cycles between modules: for every module on a cycle, the shortest cycle through it (deduplicated).

    Args:
        graph: the import graph (function-level edges included).

    Returns:
        Each cycle as its edges in order (the first import statement of each edge), sorted.
    """
    first: dict[tuple[str, str], Edge] = {}
    for e in graph.internal:
        first.setdefault((e.src, e.dst), e)
    succ: dict[str, list[str]] = {}
    for src, dst in first:
        succ.setdefault(src, []).append(dst)
    cycles: dict[tuple[str, ...], list[Edge]] = {}
    for component in _strongly_connected(sorted(graph.modules), succ):
        members = set(component)
        for start in component:
            if len(component) == 1 and (start, start) not in first:
                continue
            came_from: dict[str, str] = {}
            seen = {start}
            queue = deque([start])
            while queue:  # breadth first from start, inside the component, back to start
                node = queue.popleft()
                if (node, start) in first:
                    chain = [node]
                    while chain[-1] != start:
                        chain.append(came_from[chain[-1]])
                    chain.reverse()
                    at = chain.index(min(chain))  # the same cycle found from another member: one key
                    key = tuple(chain[at:] + chain[:at])
                    hops = [*key, key[0]]
                    cycles.setdefault(key, [first[(a, b)] for a, b in zip(hops, hops[1:])])
                    break
                for nxt in sorted(succ.get(node, [])):
                    if nxt in members and nxt not in seen:
                        seen.add(nxt)
                        came_from[nxt] = node
                        queue.append(nxt)
    return [cycles[k] for k in sorted(cycles)]


def format_cycle(cycle: Sequence[Edge]) -> str:
    """One cycle as `a -> b (file:line); b -> a (file:line)`."""
    return f"cycle of {len(cycle)}: " + "; ".join(str(e) for e in cycle)


@pytest.fixture(scope="module")
def graph() -> ImportGraph:
    return build_import_graph(ROOT, PACKAGES)


def test_every_import_points_down_the_layers(graph: ImportGraph) -> None:
    problems = layering_violations(graph, LAYERS)
    if problems:  # pytest.fail, not assert: the message is the report, without a repr of the whole graph
        pytest.fail(f"{len(problems)} import(s) break the layering:\n" + "\n".join(problems), pytrace=False)


def test_no_import_cycles(graph: ImportGraph) -> None:
    cycles = import_cycles(graph)
    if cycles:
        pytest.fail(f"{len(cycles)} import cycle(s):\n" + "\n".join(format_cycle(c) for c in cycles), pytrace=False)


def test_no_import_cycles_even_through_type_checking_imports() -> None:
    """A type-only import back into a module that imports you is still a circle between the two modules' concepts
    (the annotator app and its tools had one): none, counting `if TYPE_CHECKING:` imports too."""
    typed = build_import_graph(ROOT, PACKAGES, type_checking=True)
    assert len(typed.internal) > len(build_import_graph(ROOT, PACKAGES).internal)  # it did read more imports
    cycles = import_cycles(typed)
    if cycles:
        pytest.fail(f"{len(cycles)} import cycle(s) through TYPE_CHECKING imports:\n"
                    + "\n".join(format_cycle(c) for c in cycles), pytrace=False)


def test_graph_covers_the_package(graph: ImportGraph) -> None:
    """The scan sees the whole package: each top package, its subpackages, and lazy imports as well as eager ones."""
    for module in ("efem_viz.cli", "efem_viz.em.solver", "efem_viz.viewer.app", "annotator.app", "annotator.labels"):
        assert module in graph.modules
    assert len(graph.modules) > 50
    assert any(not e.at_import for e in graph.internal)
    assert all(e.src in graph.modules and e.dst in graph.modules for e in graph.internal)


# ---------------------------------------------------------------------------------------------- the checker itself


def _write(root: Path, files: dict[str, str]) -> None:
    for name, text in files.items():
        path = root / name
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text, encoding="utf-8")


TOY_LAYERS = Layers(
    ranks=({"base": ("toy", "toy.util")}, {"low": ("toy.low.*",)}, {"high": ("toy.high.*",), "side": ("toy.side.*",)}),
    cli=("*.commands",),
    dispatcher="toy.cli",
    core=("base", "low"),
    viser=("toy.high.*",),
)


def test_checker_reports_back_edges_cycles_and_libraries(tmp_path: Path) -> None:
    _write(tmp_path, {
        "toy/__init__.py": "",
        "toy/util.py": "import os\n",
        "toy/low/__init__.py": "",
        "toy/low/a.py": "from toy import util\n\n\ndef f():\n    from toy.high import b\n",  # lazy back edge
        "toy/low/t.py": ("from __future__ import annotations\nfrom typing import TYPE_CHECKING\n"
                         "if TYPE_CHECKING:\n    from toy.high import b\nelse:\n    import rich\n"),
        "toy/low/ui.py": "import viser\n\n\ndef g():\n    import tqdm\n",
        "toy/low/commands.py": "import tyro\nfrom toy.high import b\n",  # CLI module: may import tyro, not higher
        "toy/high/__init__.py": "",
        "toy/high/b.py": "from ..low import a\nfrom . import c\n",
        "toy/high/c.py": "def h():\n    from .b import x\n",  # b <-> c, relative and lazy
        "toy/high/d.py": "import toy.side.s\nimport toy.low.commands\nimport toy.missing\n",
        "toy/side/__init__.py": "",
        "toy/side/s.py": "import viser\n",
        "notpkg/x.py": "import toy.high.b\n",  # not a package: not scanned
    })
    graph = build_import_graph(tmp_path, ["toy"])
    assert "notpkg.x" not in graph.modules and "toy.low" in graph.modules
    assert Edge("toy.low.a", "toy.high.b", "toy/low/a.py", 5, False) in graph.internal
    assert Edge("toy.high.b", "toy.low.a", "toy/high/b.py", 1, True) in graph.internal  # `from ..low import a`
    assert Edge("toy.high.c", "toy.high.b", "toy/high/c.py", 2, False) in graph.internal
    assert not any(e.src == "toy.low.t" and e.dst.startswith("toy.high") for e in graph.internal)  # TYPE_CHECKING

    problems = layering_violations(graph, TOY_LAYERS)
    expected = [
        "toy.low.a -> toy.high.b (toy/low/a.py:5): back edge, low (layer 1) imports high (layer 2)",
        "toy.low.commands -> toy.high.b (toy/low/commands.py:2): back edge, low (layer 1) imports high (layer 2)",
        "toy.high.d -> toy.side.s (toy/high/d.py:1): sibling layers high and side do not import each other",
        "toy.high.d -> toy.low.commands (toy/high/d.py:2): only CLI modules import the CLI module toy.low.commands",
        "toy.high.d -> toy.missing (toy/high/d.py:3): no such module",
        "toy.low.t -> rich (toy/low/t.py:6): the core imports rich only inside functions (or in a CLI module)",
        "toy.low.ui -> viser (toy/low/ui.py:1): viser is imported only in toy.high.*",
        "toy.side.s -> viser (toy/side/s.py:1): viser is imported only in toy.high.*",
    ]
    assert sorted(problems) == sorted(expected)  # tqdm inside a function and tyro in a CLI module pass

    cycles = [format_cycle(c) for c in import_cycles(graph)]
    assert cycles == [
        "cycle of 2: toy.high.b -> toy.high.c (toy/high/b.py:2); toy.high.c -> toy.high.b (toy/high/c.py:2)",
        "cycle of 2: toy.high.b -> toy.low.a (toy/high/b.py:1); toy.low.a -> toy.high.b (toy/low/a.py:5)",
    ]


def test_checker_passes_a_clean_package(tmp_path: Path) -> None:
    _write(tmp_path, {"toy/__init__.py": "", "toy/util.py": "", "toy/low/__init__.py": "from . import a\n",
                      "toy/low/a.py": "from toy import util\n", "toy/high/__init__.py": "",
                      "toy/high/b.py": "import toy.low.a\n\n\ndef f():\n    import viser\n"})
    graph = build_import_graph(tmp_path, ["toy"])
    assert len(graph.internal) == 3
    assert layering_violations(graph, TOY_LAYERS) == [] and import_cycles(graph) == []


# ------------------------------------------------------------------------------------------------------ run time

_PROBE = r"""
import importlib, json, sys, traceback

first, rest = json.loads(sys.argv[1])
pulled, failed = {}, {}


class ViserProbe:
    '''Records which package modules are being imported when viser is first found.'''

    def find_spec(self, name, path=None, target=None):
        if name == "viser":
            chain, frame = [], sys._getframe(1)
            while frame is not None:
                mod = frame.f_globals.get("__name__", "")
                if mod.split(".")[0] in ("efem_viz", "annotator"):
                    chain.append(f"{mod}:{frame.f_lineno}")
                frame = frame.f_back
            self.chain = " <- ".join(chain)
        return None


probe = ViserProbe()
sys.meta_path.insert(0, probe)
for module in first + rest:
    try:
        importlib.import_module(module)
    except BaseException:
        failed[module] = traceback.format_exc(limit=-3)
    if module in first and "viser" in sys.modules:
        pulled[module] = getattr(probe, "chain", "?")
        probe.chain = "?"
        for name in [m for m in sys.modules if m == "viser" or m.startswith("viser.")]:
            del sys.modules[name]
print(json.dumps({"failed": failed, "pulled": pulled}))
"""


@pytest.fixture(scope="module")
def runtime_imports(graph: ImportGraph) -> dict[str, dict[str, str]]:
    """Import every module in one fresh interpreter: those that must stay free of viser first, then the rest."""
    light = [m for m in graph.modules if not any(matches(m, p) for p in LAYERS.viser)]
    heavy = [m for m in graph.modules if m not in light]
    out = subprocess.run([sys.executable, "-c", _PROBE, json.dumps([light, heavy])], capture_output=True, text=True,
                         timeout=300, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_every_module_imports(runtime_imports: dict[str, dict[str, str]]) -> None:
    failed = runtime_imports["failed"]
    if failed:
        pytest.fail("modules that fail to import:\n" + "\n".join(f"{m}:\n{tb}" for m, tb in failed.items()),
                    pytrace=False)


def test_only_the_apps_load_viser(runtime_imports: dict[str, dict[str, str]]) -> None:
    pulled = runtime_imports["pulled"]
    if pulled:
        pytest.fail("importing these loads viser (importer chain, innermost first):\n" + "\n".join(
            f"{m}: {chain}" for m, chain in pulled.items()), pytrace=False)


def test_cli_dispatcher_is_light() -> None:
    code = "import sys; import efem_viz.cli; print(sorted(m for m in ('torch','open3d','viser') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_cli_usage_and_unknown_command(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--help"]) == 0
    assert "segment" in capsys.readouterr().out
    assert cli.main(["no-such-command"]) == 2
    assert "unknown command" in capsys.readouterr().err


@pytest.mark.parametrize("name", sorted(cli.SUBCOMMANDS))
def test_every_subcommand_resolves(name: str) -> None:
    import importlib

    module_name, cls_name = cli.SUBCOMMANDS[name][0].split(":")
    cls = getattr(importlib.import_module(module_name), cls_name)
    assert callable(getattr(cls, "run", None)), f"{cls_name} has no run()"


HEADLESS_SESSIONS = ("efem_viz.viewer.session", "annotator.session")
"""The apps' headless sessions (ARCHITECTURE.md "The apps"): drivable from a script with no GUI library loaded."""
DRAWING_MODULES = (
    "efem_viz.viewer.app", "efem_viz.viewer.wiring", "efem_viz.viewer.nodes", "efem_viz.viewer.panels",
    "efem_viz.viewer.panel_views", "efem_viz.viewer.scene_views", "efem_viz.viewer.legend",
    "efem_viz.viewer.label_layout", "annotator.app", "annotator.panels", "annotator.panel_views",
    "annotator.scan_view", "annotator.render", "annotator.wiring", "annotator.cheat_sheet",
)
"""The modules that draw (scene nodes, panels and what fills them, the legend, label placement) or wire the GUI;
every module that imports viser anywhere (even for types only) counts too (`drawing_modules`)."""


def imports_viser(path: Path) -> bool:
    """Whether a module's source imports viser anywhere (module level, functions, `if TYPE_CHECKING:`)."""
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                 else [node.module or ""] if isinstance(node, ast.ImportFrom) and node.level == 0 else [])
        if any(n == "viser" or n.startswith("viser.") for n in names):
            return True
    return False


def drawing_modules(graph: ImportGraph) -> list[str]:
    """`DRAWING_MODULES` and every module of the package that imports viser."""
    found = {m for m, path in graph.modules.items() if imports_viser(path)}
    missing = [m for m in DRAWING_MODULES if m not in graph.modules]
    assert not missing, f"DRAWING_MODULES names modules that do not exist: {missing}"
    return sorted(found | set(DRAWING_MODULES))


_LOADED = """
import importlib, json, sys
importlib.import_module(sys.argv[1])
watched = set(json.loads(sys.argv[2]))
print(json.dumps(sorted(m for m in sys.modules if m in watched or m == "viser" or m.startswith("viser."))))
"""


@pytest.mark.parametrize("session", HEADLESS_SESSIONS)
def test_sessions_load_no_viser_and_no_drawing_module(graph: ImportGraph, session: str) -> None:
    """Headless means headless: importing a session (in a fresh interpreter) loads neither viser nor a module that
    draws, directly or through anything it imports."""
    drawing = drawing_modules(graph)
    assert session not in drawing
    out = subprocess.run([sys.executable, "-c", _LOADED, session, json.dumps(drawing)], capture_output=True,
                         text=True, timeout=120, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    assert loaded == [], f"importing {session} loads {loaded}"


def test_drawing_module_detection_sees_type_only_imports(tmp_path: Path) -> None:
    """The viser detector finds imports under `if TYPE_CHECKING:` and in functions, and ignores mentions."""
    typed = tmp_path / "typed.py"
    typed.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from viser import GuiApi\n")
    lazy = tmp_path / "lazy.py"
    lazy.write_text("def f():\n    import viser.transforms\n")
    plain = tmp_path / "plain.py"
    plain.write_text('"""No viser here."""\nimport viserlike\n')
    assert imports_viser(typed) and imports_viser(lazy) and not imports_viser(plain)
