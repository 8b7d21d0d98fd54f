"""The package's layering, checked on the import graph (every import statement, also inside functions).

Layers, bottom up: ``tagloc.core`` (types, sticker, map, camera, rig, geometry, errors); ``tracker``
and ``tagloc.vision`` beside each other on it; ``tagloc.io``; ``tagloc.pipeline`` and ``tagloc.sim``;
``tagloc.eval``; ``tagloc.apps``; ``tagloc.cli``. A package may import its own modules and the
packages listed for it below, nothing else; no two modules may import each other, directly or round
a longer loop.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components

ROOT = Path(__file__).resolve().parents[1]

ALLOWED = {
    "tagloc.core": set(),
    "tracker": {"tagloc.core"},
    "tagloc.vision": {"tagloc.core"},
    "tagloc.io": {"tagloc.core"},
    "tagloc.pipeline": {"tagloc.core", "tagloc.vision", "tracker", "tagloc.io"},
    "tagloc.sim": {"tagloc.core", "tagloc.io"},
    "tagloc.eval": {"tagloc.core", "tagloc.vision", "tracker", "tagloc.io", "tagloc.pipeline", "tagloc.sim"},
    "tagloc.apps": {
        "tagloc.core",
        "tagloc.vision",
        "tracker",
        "tagloc.io",
        "tagloc.pipeline",
        "tagloc.sim",
        "tagloc.eval",
    },
    "tagloc.cli": {
        "tagloc",
        "tagloc.core",
        "tagloc.vision",
        "tracker",
        "tagloc.io",
        "tagloc.pipeline",
        "tagloc.sim",
        "tagloc.eval",
        "tagloc.apps",
    },
    "tagloc": {"tagloc.core", "tagloc.cli"},  # the package's own __init__ and __main__
}


def module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def layer_of(module: str) -> str:
    for layer in sorted(ALLOWED, key=len, reverse=True):
        if module == layer or module.startswith(layer + "."):
            return layer
    raise AssertionError(f"{module} belongs to no layer: add its package to ALLOWED")


def _imported_by_call(node: ast.AST) -> str | None:
    """The module a call ``importlib.import_module("a.b")`` or ``__import__("a.b")`` imports (a
    literal name only), else None: a layer must not be crossed by naming the module in a string."""
    if not (isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant)):
        return None
    f = node.func
    name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else None
    arg = node.args[0].value
    return arg if name in ("import_module", "__import__") and isinstance(arg, str) else None


def import_graph() -> dict[str, set[str]]:
    """Each project module and the project modules it imports (resolved to modules that exist)."""
    files = [p for top in ("tagloc", "tracker") for p in (ROOT / top).rglob("*.py")]
    modules = {module_name(p): p for p in files}
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                # "from a.b import c" names module a.b.c when it exists, else a.b.
                cands = [f"{node.module}.{a.name}" for a in node.names] + [node.module]
            elif isinstance(node, ast.ImportFrom):
                raise AssertionError(f"{path}: use absolute imports")
            elif isinstance(node, ast.Import):
                cands = [a.name for a in node.names]
            elif (called := _imported_by_call(node)) is not None:
                cands = [called]
            else:
                continue
            for c in cands:
                if c.split(".")[0] in ("tagloc", "tracker") and c in modules:
                    targets.add(c)
        graph[name] = targets - {name}
    return graph


def test_every_import_respects_the_layers():
    bad = []
    for mod, targets in import_graph().items():
        own = layer_of(mod)
        for t in targets:
            other = layer_of(t)
            if other != own and other not in ALLOWED[own]:
                bad.append(f"{mod} -> {t} ({own} may not import {other})")
    assert not bad, "\n".join(sorted(bad))


def test_no_import_cycles():
    graph = import_graph()
    names = sorted(graph)
    index = {n: i for i, n in enumerate(names)}
    rows = [index[a] for a in names for b in graph[a]]
    cols = [index[b] for a in names for b in graph[a]]
    adj = csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(len(names), len(names)))
    _, labels = connected_components(adj, directed=True, connection="strong")
    groups = [[n for n in names if labels[index[n]] == g] for g in set(labels)]
    cycles = [g for g in groups if len(g) > 1]
    assert not cycles, f"import cycles: {cycles}"


def test_the_checker_sees_a_violation(tmp_path, monkeypatch):
    """The rule fires: a vision module importing the tracker is reported."""
    assert "tracker" not in ALLOWED["tagloc.vision"]
    assert layer_of("tagloc.vision.detect") == "tagloc.vision"
    assert layer_of("tracker.ekf") == "tracker"
    assert layer_of("tagloc.cli") == "tagloc.cli" and layer_of("tagloc.__main__") == "tagloc"
    graph = import_graph()
    assert "tagloc.core.errors" in graph["tagloc.vision.detect"]  # imports are seen
    assert "tagloc.vision.paper_detector" in graph["tagloc.vision.detect"]  # also inside functions


def test_the_checker_sees_the_trackers_imports_and_string_imports():
    """The tracker's imports are seen (all of them in tagloc's bottom layer, ``tagloc.core``), and a
    module imported by naming it in a string is an import like any other."""
    assert ALLOWED["tracker"] == {"tagloc.core"}
    graph = import_graph()
    assert {"tagloc.core.types", "tagloc.core.geometry"} <= graph["tracker.tracker"]
    assert {layer_of(t) for t in graph["tracker.tracker"]} == {"tracker", "tagloc.core"}
    for code in ('importlib.import_module("tagloc.io.session")', '__import__("tagloc.io.session")'):
        assert _imported_by_call(ast.parse(code).body[0].value) == "tagloc.io.session"
    assert _imported_by_call(ast.parse('importlib.import_module(f"tagloc.cli.{x}")').body[0].value) is None
