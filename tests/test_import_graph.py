"""The package's import graph (issue #48): no file imports itself through others, and no report imports a runner.

Every file under rlsac/ is parsed (never imported): module-level and function-level imports alike, relative ones
resolved, `from pkg import name` counted as importing pkg/name.py when that is a module. Importing a package
counts as importing its __init__.py, and importing pkg.sub also runs pkg/__init__.py, except where pkg holds the
importing file (its own packages have run before it): `from rlsac.tasks import line` in rlsac/tasks/essential.py
imports rlsac/tasks/line.py only, while `from rlsac.tasks import register_task` imports rlsac/tasks/__init__.py.
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "rlsac"

# the runners: modules that run a protocol's stages (train, tune, evaluate, select) and write results; the reports
# read what they wrote (rlsac.evaluation.results, rlsac.layout.protocol) and never call them. rlsac.rl.ngransac
# holds NG-RANSAC's network and sampler since issue #48 (its training is the learner rlsac.learners.ngransac); no report
# needs it either
RUNNERS = (
    "rlsac.experiments.folds",
    "rlsac.experiments.folds_retune",
    "rlsac.experiments.selection",
    "rlsac.evaluation.train",
    "rlsac.evaluation.evaluate",
    "rlsac.rl.ngransac",
    "rlsac.learners",
    "rlsac.experiments.ablate",
    "rlsac.experiments.scale",
    "rlsac.experiments.ladder",
    "rlsac.runners.pipeline",
    "rlsac.runners.schedule",
    "rlsac.runners.stage_task",
    "rlsac.runners.warm",
    "rlsac.experiments.quick",
)

# the layers of the package, lowest first, by package (issue #65): a file imports files of its own layer or of lower
# ones, never of a higher one (a name ending in "*" covers the package and everything in it). docs/layout.md draws it
LAYERS = (
    # the core: errors, numeric modes, configs and params, files, devices, progress bars, signals, MLflow
    ("rlsac", "rlsac.errors", "rlsac.numerics", "rlsac.config", "rlsac.io", "rlsac.devices", "rlsac.progress",
     "rlsac.signals", "rlsac.tracking"),
    # the maths of two views and of the scores
    ("rlsac.maths*",),
    # the protocol's vocabulary (names, paths, budgets) and the data files
    ("rlsac.layout*", "rlsac.data*"),
    # the estimation problems
    ("rlsac.tasks*",),
    # our RANSAC loop's parts and the classical estimators
    ("rlsac.estimation*",),
    # the learned samplers: RLSAC's environment, policy and agent, NG-RANSAC's network, the checkpoint format
    ("rlsac.rl*",),
    # one method or learner run once: the registries, evaluate, train, tuning, the result readers
    ("rlsac.evaluation*", "rlsac.learners*"),
    # the reports: tables and figures from the results
    ("rlsac.reports*",),
    # the studies and what runs their stages
    ("rlsac.experiments*", "rlsac.runners*", "rlsac.commands"),
    # the command line
    ("rlsac.cli",),
)


def _modules() -> dict[str, Path]:
    """dotted module name -> file, for every .py under rlsac/ (a package is its __init__.py)."""
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = path
    return out


def _imports(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """The modules of the package that `name` imports anywhere in its file (parents' __init__ included)."""
    is_pkg = path.name == "__init__.py"
    own = name.split(".") if is_pkg else name.split(".")[:-1]
    ancestors = {".".join(own[:i]) for i in range(1, len(own) + 1)}  # packages that hold this file
    found: set[str] = set()

    def add(target: str, explicit: bool = True) -> None:
        parts = target.split(".")
        for i in range(1, len(parts) + 1):  # importing a.b.c runs a, a.b and a.b.c
            prefix = ".".join(parts[:i])
            if prefix in modules and (prefix not in ancestors or (explicit and prefix == target)):
                found.add(prefix)

    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = name.split(".") if is_pkg else name.split(".")[:-1]
                base = base[: len(base) - (node.level - 1)]
                module = ".".join(base + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            subs = [f"{module}.{alias.name}" for alias in node.names]
            # `from pkg import sub` needs only pkg's submodule; `from pkg import name` needs pkg/__init__.py
            add(module, explicit=not all(sub in modules for sub in subs))
            for sub in subs:
                if sub in modules:
                    add(sub)
    found.discard(name)
    return found


def import_graph() -> dict[str, set[str]]:
    modules = _modules()
    return {name: _imports(name, path, modules) for name, path in modules.items()}


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph as [a, b, ..., a], or None."""
    white, grey, black = 0, 1, 2
    colour = dict.fromkeys(graph, white)
    stack: list[str] = []

    def visit(node: str) -> list[str] | None:
        colour[node] = grey
        stack.append(node)
        for nxt in sorted(graph[node]):
            if colour[nxt] == grey:
                return stack[stack.index(nxt):] + [nxt]
            if colour[nxt] == white:
                cycle = visit(nxt)
                if cycle:
                    return cycle
        stack.pop()
        colour[node] = black
        return None

    for node in sorted(graph):
        if colour[node] == white:
            cycle = visit(node)
            if cycle:
                return cycle
    return None


def all_cycles(graph: dict[str, set[str]]) -> list[set[str]]:
    """The strongly connected components with more than one file (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on: set[str] = set()
    stack: list[str] = []
    out: list[set[str]] = []

    def strong(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = set()
            while True:
                w = stack.pop()
                on.discard(w)
                comp.add(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(comp)

    for v in sorted(graph):
        if v not in index:
            strong(v)
    return out


def layer_of(name: str) -> int | None:
    for i, layer in enumerate(LAYERS):
        for pat in layer:
            if name == pat or (pat.endswith("*") and (name == pat[:-1] or name.startswith(pat[:-1] + "."))):
                return i
    return None


def upward_imports(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(importer, imported) where the imported file lies in a higher layer than its importer."""
    return sorted((a, b) for a, targets in graph.items() for b in targets if layer_of(b) > layer_of(a))


def test_graph_sees_the_package():
    graph = import_graph()
    assert "rlsac.cli" in graph and "rlsac.reports.tables" in graph
    assert "rlsac.numerics" in graph["rlsac"]  # rlsac/__init__.py imports it
    assert {"rlsac.data", "rlsac.data.lines"} <= graph["rlsac.tasks.line"]  # `from rlsac.data import lines`
    assert "rlsac" not in graph["rlsac.cli"]  # its own package has run before it


def test_no_import_cycles():
    graph = import_graph()
    knots = all_cycles(graph)
    cycle = find_cycle(graph)
    assert cycle is None, f"import cycle: {' -> '.join(cycle)}; every knot: {[sorted(k) for k in knots]}"


def test_reports_import_no_runner():
    graph = import_graph()
    bad = {
        (name, target)
        for name, targets in graph.items()
        if name.startswith("rlsac.reports")
        for target in targets
        if any(target == r or target.startswith(r + ".") for r in RUNNERS)
    }
    assert not bad, f"reports importing runners: {sorted(bad)}"


def test_every_file_has_a_layer():
    assert not [m for m in import_graph() if layer_of(m) is None]


def test_no_import_runs_back_up():
    up = upward_imports(import_graph())
    assert not up, f"imports of a higher layer: {up}"


def test_protocol_imports_nothing_above_config():
    assert import_graph()["rlsac.layout.protocol"] <= {"rlsac.errors", "rlsac.config"}


def _reach(graph: dict[str, set[str]], start: str) -> set[str]:
    seen, todo = set(), [start]
    while todo:
        for nxt in graph[todo.pop()] - seen:
            seen.add(nxt)
            todo.append(nxt)
    return seen


def test_learners_are_peers_on_one_harness():
    graph = import_graph()
    learners = ("rlsac.learners.sac", "rlsac.learners.ngransac")
    for a in learners:
        assert "rlsac.learners.harness" in graph[a]
        assert not (set(learners) - {a}) & _reach(graph, a), f"{a} imports the other learner"
    assert not set(learners) & _reach(graph, "rlsac.learners.harness")


def test_train_methods_are_the_learner_registry():
    """`rlsac train --method` offers the registered learners (the CLI lists them without importing torch)."""
    from rlsac.cli import cli
    from rlsac.learners import LEARNERS, OWN_SECTIONS

    option = next(p for p in cli.commands["train"].params if p.name == "method")
    assert list(option.type.choices) == list(LEARNERS) == list(OWN_SECTIONS) == ["rlsac", "ngransac"]


# the modules directly in rlsac/ (issue #65: about a dozen): the core, the small commands and the command line
ROOT_MODULES = {"__init__", "cli", "commands", "config", "devices", "errors", "io", "numerics", "progress", "signals",
                "tracking"}


def test_the_root_holds_the_core_and_every_package_says_what_lives_there():
    assert {p.stem for p in PKG.glob("*.py")} == ROOT_MODULES
    layout = (PKG.parent / "docs" / "layout.md").read_text()
    for init in sorted(PKG.glob("*/__init__.py")):
        doc = ast.get_docstring(ast.parse(init.read_text()))
        assert doc, f"{init}: a package's __init__ says what lives there"
        assert f"  {init.parent.name}/" in layout, f"docs/layout.md does not describe {init.parent.name}/"
    # every package is in a layer of its own name (no module of a package placed by a name of the flat root)
    for pkg in sorted(p.parent.name for p in PKG.glob("*/__init__.py")):
        assert any(f"rlsac.{pkg}*" in layer for layer in LAYERS), f"rlsac.{pkg} has no layer"
