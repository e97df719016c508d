"""The package's shape: its import graph has no cycle and no import from a later stage into an earlier one.

Read from the source with `ast` (nothing is imported), counting every import, the lazy ones inside functions
included, except those under ``if TYPE_CHECKING:``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / "pytest_drivedegrade"
NAME = "pytest_drivedegrade"

#: The pipeline's stages, earliest first; a module may import only from its own stage or earlier ones. A
#: module belongs to the first stage whose prefix it matches (`scoring.records` before `scoring`).
STAGES: tuple[tuple[str, ...], ...] = (
    ("constants", "errors", "atomic", "progress", ""),  # "" is the package's own __init__ (the lazy public API)
    ("corruptions",),
    ("data",),
    ("planning", "metrics"),  # the contract a plan must meet, and how one plan is scored
    ("cells",),  # which cells exist, what one yields, bit-identity
    ("loader", "run", "store", "shards", "raypool", "floor"),  # running a cell (shards, Ray actors); the floor
    ("scoring",),  # statistics over finished cells
    ("report", "certificate"),  # the certificate (seal, verify, merge, reproduce, compare, estimate) and rendering
    ("plugin", "cli"),
)


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = [p for p in rel.parts if p != "__init__"]
    return ".".join(parts)


def stage_of(module: str) -> int:
    for rank, prefixes in enumerate(STAGES):
        for prefix in prefixes:
            if module == prefix or (prefix and module.startswith(prefix + ".")):
                return rank
    raise AssertionError(f"module {module!r} belongs to no stage: add it to STAGES in {__file__}")


def _type_checking_blocks(tree: ast.AST) -> set[int]:
    """ids of import nodes under `if TYPE_CHECKING:`."""
    skip: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            skip.update(id(n) for child in node.body for n in ast.walk(child))
    return skip


def imports_of(path: Path) -> set[str]:
    """Package-internal modules imported by `path` (relative imports resolved; `from . import x` counts the
    submodule x, not the package)."""
    tree = ast.parse(path.read_text())
    skip = _type_checking_blocks(tree)
    here = module_name(path).split(".") if module_name(path) else []
    package = here if path.name == "__init__.py" else here[:-1]
    found: set[str] = set()
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            found |= {a.name[len(NAME) + 1:] for a in node.names if a.name.startswith(NAME + ".")}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[:len(package) - node.level + 1]
                target = ".".join([*base, *(node.module.split(".") if node.module else [])])
            elif node.module and (node.module == NAME or node.module.startswith(NAME + ".")):
                target = node.module[len(NAME) + 1:]
            else:
                continue
            for alias in node.names:  # `from . import x` imports the submodule x; `from .m import f` imports m
                sub = f"{target}.{alias.name}".strip(".")
                is_module = (PACKAGE / Path(*sub.split("."))).with_suffix(".py").exists() \
                    or (PACKAGE / Path(*sub.split("."))).is_dir()
                found.add(sub if is_module else target)
    me = module_name(path)
    # A module's own ancestor packages are imported before it anyway: importing a name from one is no edge.
    ancestors = {".".join(me.split(".")[:i]) for i in range(len(me.split(".")))}
    return {m for m in found if m != me and m not in ancestors}


def graph() -> dict[str, set[str]]:
    return {module_name(p): imports_of(p) for p in sorted(PACKAGE.rglob("*.py"))}


def test_every_module_has_a_stage():
    for module in graph():
        stage_of(module)


def test_no_import_from_a_later_stage():
    back = sorted(f"{m} (stage {stage_of(m)}) imports {t} (stage {stage_of(t)})"
                  for m, targets in graph().items() for t in targets if stage_of(t) > stage_of(m))
    assert not back, "back edges:\n" + "\n".join(back)


def test_no_import_cycle():
    full = graph()
    g = {m: {t for t in ts if t in full} for m, ts in full.items()}
    state: dict[str, int] = {}
    stack: list[str] = []

    def visit(m: str) -> None:
        state[m] = 1
        stack.append(m)
        for t in sorted(g[m]):
            if state.get(t) == 1:
                cycle = stack[stack.index(t):] + [t]
                pytest.fail("import cycle: " + " -> ".join(cycle))
            if t not in state:
                visit(t)
        stack.pop()
        state[m] = 2

    for m in sorted(g):
        if m not in state:
            visit(m)


def test_the_checker_sees_back_edges_and_cycles(tmp_path, monkeypatch):
    """The graph reader itself: a relative import up and a lazy import inside a function are both edges."""
    pkg = tmp_path / NAME
    (pkg / "scoring").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "scoring" / "__init__.py").write_text("")
    (pkg / "cells.py").write_text("def f():\n    from .scoring import verdict\n")
    (pkg / "scoring" / "verdict.py").write_text("from ..cells import f\n")
    monkeypatch.setattr(__import__(__name__), "PACKAGE", pkg)
    assert imports_of(pkg / "cells.py") == {"scoring.verdict"}
    assert imports_of(pkg / "scoring" / "verdict.py") == {"cells"}
    with pytest.raises(AssertionError, match="back edges"):
        test_no_import_from_a_later_stage()
    with pytest.raises(pytest.fail.Exception, match="import cycle: cells -> scoring.verdict -> cells"):
        test_no_import_cycle()
