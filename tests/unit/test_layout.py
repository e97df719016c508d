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

#: The pipeline's stages, earliest first; a module may import only from its own stage or earlier ones. Each entry
#: is a whole top-level module or folder of the package, and a module belongs to the stage of its top level
#: (`metrics.pdms.rules` is in `metrics`' stage): a folder is one stage, with no exception for a submodule.
STAGES: tuple[tuple[str, ...], ...] = (
    ("constants", "errors", "atomic", "settings", "progress", ""),  # "" is the package's own __init__ (lazy API)
    ("corruptions",),
    ("data",),
    ("planning", "metrics"),  # the contract a plan must meet, and how one plan is scored
    ("cells", "payload"),  # which cells exist, what one yields, bit-identity; how a finished one travels
    # running a cell: decode and inject, the threads beside the planner, calling it, the run, stored cells, shards,
    # Ray actors; the ego-only floor
    ("loader", "pacing", "timelimit", "stream", "run", "store", "shards", "rayactor", "raypool", "floor"),
    ("closedloop",),  # the closed loop: routes of the world, simulator, run and cell scores (spec 13)
    ("foreign",),  # a model's own evaluator: the cells it runs (ladder), its per-cell table read into cell records
    ("scoring",),  # statistics over finished cells
    ("certificate",),  # the certificate: seal, sign, verify, merge, reproduce, compare, estimate; a FinishedRun
    ("report",),  # rendering: the one end of a run (publish), cells.csv, certificate.json, HTML, JUnit, terminal
    ("plugin", "cli"),
)


def module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE).with_suffix("")
    parts = [p for p in rel.parts if p != "__init__"]
    return ".".join(parts)


def top_level(module: str) -> str:
    """The top-level module or folder of the package a module lies in ("" for the package's __init__)."""
    return module.split(".")[0]


def stage_of(module: str) -> int:
    for rank, names in enumerate(STAGES):
        if top_level(module) in names:
            return rank
    raise AssertionError(f"module {module!r} belongs to no stage: add {top_level(module)!r} to STAGES in {__file__}")


def top_levels() -> set[str]:
    """The package's top-level modules and folders (those holding Python files), and "" for its __init__."""
    names = {p.stem for p in PACKAGE.glob("*.py") if p.name != "__init__.py"}
    names |= {p.name for p in PACKAGE.iterdir() if p.is_dir() and any(p.rglob("*.py"))}
    return names | {""}


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


def test_folders_match_stages():
    """Each STAGES entry is a whole top-level module or folder, named once; every top-level module and folder
    is named; and every module inside a folder (`metrics/pdms/rules.py`) sits in its folder's stage."""
    entries = [name for names in STAGES for name in names]
    assert not [e for e in entries if "." in e], "a STAGES entry names a submodule: stages are whole folders"
    assert len(entries) == len(set(entries)), "a top-level module or folder is named in two stages"
    assert set(entries) == top_levels(), (f"not in STAGES: {sorted(top_levels() - set(entries))}; "
                                          f"in STAGES but not in the package: {sorted(set(entries) - top_levels())}")
    for module in graph():
        assert stage_of(module) == stage_of(top_level(module)), module


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


def test_the_checker_sees_a_submodule_entry_and_a_missing_folder(tmp_path, monkeypatch):
    """The folder check itself: a stage naming a submodule, and a top-level folder no stage names, both fail."""
    pkg = tmp_path / NAME
    (pkg / "metrics" / "pdms").mkdir(parents=True)
    for path in ("__init__.py", "metrics/__init__.py", "metrics/pdms/__init__.py", "metrics/pdms/rules.py"):
        (pkg / path).write_text("")
    module = __import__(__name__)
    monkeypatch.setattr(module, "PACKAGE", pkg)
    monkeypatch.setattr(module, "STAGES", (("",), ("metrics",)))
    test_folders_match_stages()  # the whole folder in one stage: fine
    monkeypatch.setattr(module, "STAGES", (("",), ("metrics",), ("metrics.pdms",)))
    with pytest.raises(AssertionError, match="names a submodule"):
        test_folders_match_stages()
    (pkg / "floor.py").write_text("")
    monkeypatch.setattr(module, "STAGES", (("",), ("metrics",)))
    with pytest.raises(AssertionError, match=r"not in STAGES: \['floor'\]"):
        test_folders_match_stages()


#: The size a reader can hold in mind (STYLE.md): a module under this many lines, a function under `FUNCTION_LINES`.
MODULE_LINES = 450
FUNCTION_LINES = 60
#: `Any` in annotations may only fall: the second pass of issue 19 halved it (344 -> at most 172); a new `Any`
#: takes the place of one removed, or a real type.
ANY_BUDGET = 172


def _modules(root: Path) -> list[Path]:
    return sorted(p for p in root.rglob("*.py") if "__pycache__" not in p.parts)


def long_parts(root: Path) -> list[str]:
    """Modules over MODULE_LINES lines and functions over FUNCTION_LINES lines below `root`, named."""
    out = []
    for path in _modules(root):
        text = path.read_text()
        name = path.relative_to(root).as_posix()
        if text.count("\n") > MODULE_LINES:
            out.append(f"{name}: {text.count(chr(10))} lines")
        for node in ast.walk(ast.parse(text)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                length = (node.end_lineno or node.lineno) - node.lineno + 1
                if length > FUNCTION_LINES:
                    out.append(f"{name}:{node.lineno} {node.name}(): {length} lines")
    return out


def any_annotations(root: Path) -> int:
    """How many times `Any` is named in the annotations (arguments, returns, annotated names) below `root`."""
    count = 0
    for path in _modules(root):
        for node in ast.walk(ast.parse(path.read_text())):
            notes: list[ast.expr] = []
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                a = node.args
                notes += [x.annotation for x in [*a.posonlyargs, *a.args, *a.kwonlyargs, a.vararg, a.kwarg]
                          if x is not None and x.annotation is not None]
                notes += [node.returns] if node.returns is not None else []
            elif isinstance(node, ast.AnnAssign):
                notes.append(node.annotation)
            count += sum(isinstance(x, ast.Name) and x.id == "Any" for note in notes for x in ast.walk(note))
    return count


def test_modules_and_functions_stay_readable():
    assert long_parts(PACKAGE) == []


def test_any_in_annotations_stays_within_budget():
    assert any_annotations(PACKAGE) <= ANY_BUDGET


def test_the_size_checks_see_what_they_count(tmp_path):
    """The counters themselves, on a made-up package: a long function, a long module, three `Any`s."""
    body = "\n".join(f"    x{i} = {i}" for i in range(FUNCTION_LINES))
    (tmp_path / "long.py").write_text(f"def f() -> None:\n{body}\n" + "\n" * MODULE_LINES)
    (tmp_path / "typed.py").write_text("from typing import Any\nv: Any = 1\n"
                                       "def g(a: Any, *b: int) -> dict[str, Any]:\n    return {}\n")
    assert long_parts(tmp_path) == [f"long.py: {FUNCTION_LINES + 1 + MODULE_LINES} lines",
                                    f"long.py:1 f(): {FUNCTION_LINES + 1} lines"]
    assert any_annotations(tmp_path) == 3
