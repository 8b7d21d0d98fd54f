"""The code standards that a parser can check, on the tracker and tagloc's core and pipeline: every
public function, method and property has type hints and a docstring, and every public class a
docstring (dunder methods other than ``__call__`` are left to their protocol's meaning)."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CHECKED = ("tracker", "tagloc/core", "tagloc/pipeline")


def _gaps(path: Path) -> list[str]:
    """What ``path``'s public definitions lack, one line each (``file:line: name: what``)."""
    out: list[str] = []
    where = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path.name

    def visit(node: ast.AST, owner: str | None) -> None:
        for n in ast.iter_child_nodes(node):
            if isinstance(n, ast.ClassDef):
                if not n.name.startswith("_"):
                    if ast.get_docstring(n) is None:
                        out.append(f"{where}:{n.lineno}: class {n.name}: docstring")
                    visit(n, n.name)
            elif isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef)):
                dunder = n.name.startswith("__") and n.name.endswith("__")
                if (n.name.startswith("_") and not dunder) or (dunder and n.name not in ("__init__", "__call__")):
                    continue
                args = [
                    a for a in (*n.args.posonlyargs, *n.args.args, *n.args.kwonlyargs) if a.arg not in ("self", "cls")
                ]
                args += [a for a in (n.args.vararg, n.args.kwarg) if a is not None]
                what = [f"hint for {a.arg}" for a in args if a.annotation is None]
                if n.returns is None:
                    what.append("return hint")
                if ast.get_docstring(n) is None and n.name != "__init__":
                    what.append("docstring")
                if what:
                    name = f"{owner}.{n.name}" if owner else n.name
                    out.append(f"{where}:{n.lineno}: {name}: {', '.join(what)}")

    visit(ast.parse(path.read_text(), str(path)), None)
    return out


def test_public_definitions_have_hints_and_docstrings():
    gaps = [g for top in CHECKED for p in sorted((ROOT / top).rglob("*.py")) for g in _gaps(p)]
    assert not gaps, "\n".join(gaps)


def test_the_check_sees_a_gap(tmp_path):
    """A public function without hints or docstring, and an undocumented class, are reported; private
    ones and dunder methods are not."""
    p = tmp_path / "probe.py"
    p.write_text(
        "class A:\n    def __len__(self):\n        return 0\n\n"
        "    def f(self, x):\n        return x\n\n\ndef _g(y):\n    return y\n"
    )
    gaps = _gaps(p)
    assert [g.split(": ", 1)[1] for g in gaps] == ["class A: docstring", "A.f: hint for x, return hint, docstring"]
