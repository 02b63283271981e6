"""The two trees and the library's floors (docs/architecture.md): the library (``difffilter/``) never
imports the research tree (``experiments/``); inside the library a module may import only from its
own floor or the floors below; no import hides inside a function body (except optional
dependencies); one paper's package never imports another's; the Hydra entry points put the
repository root on ``sys.path`` in one stated line and nothing else.

The rules are read off the source with ``ast``, so a violation is found even in a module no other
test imports.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "difffilter"

#: Floors from the bottom up.  Modules of one floor may import each other; ``smoothers`` is the
#: floor a smoother package takes when it exists.
FLOORS: list[set[str]] = [
    {"_openmp", "_util", "constraints", "geometry", "linalg", "params", "selection", "threads"},
    {"datasets"},  # file formats and the data-set registry: numpy only, below every model
    {"models"},
    {"filters"},
    {"mixers"},
    {"smoothers"},
    {"sim"},
    {"engines", "func"},
    {"evaluate"},
    {"learn"},
]
#: Units that may import every floor (the package root re-exports).
ABOVE_ALL_BUT_PAPERS = {"__init__"}
EXPERIMENTS = ROOT / "experiments"
#: Third-party packages that are optional (extras ``test``/``bench``): importing them lazily,
#: inside the function that needs them, is how their absence stays harmless.
OPTIONAL = {"dynamax", "filterpy", "jax", "mpmath", "scipy"}


def _rank(unit: str) -> float:
    for i, floor in enumerate(FLOORS):
        if unit in floor:
            return float(i)
    if unit in ABOVE_ALL_BUT_PAPERS:
        return float(len(FLOORS))
    raise AssertionError(f"difffilter.{unit} is on no floor: add it to FLOORS in tests/test_layering.py")


def _modules(package: Path) -> list[tuple[Path, list[str]]]:
    out = []
    for path in sorted(package.rglob("*.py")):
        parts = ["difffilter", *path.relative_to(package).with_suffix("").parts]
        out.append((path, parts))
    return out


def _unit(parts: list[str]) -> str:
    """The floor unit of module ``parts`` (``["difffilter", "filters", "ukf"]`` -> ``"filters"``)."""
    return parts[1] if len(parts) > 1 else "__init__"


def _imported(node: ast.Import | ast.ImportFrom, parts: list[str], is_package: bool) -> list[list[str]]:
    """Dotted module paths (as part lists) an import statement reaches."""
    if isinstance(node, ast.Import):
        return [alias.name.split(".") for alias in node.names]
    if node.level == 0:
        base = (node.module or "").split(".")
    else:
        package = parts if is_package else parts[:-1]
        base = package[: len(package) - (node.level - 1)] + ((node.module or "").split(".") if node.module else [])
    if node.module is None:  # from . import geometry, linalg
        return [base + [alias.name] for alias in node.names]
    return [base]


def _walk(tree: ast.AST, in_function: bool = False):
    for child in ast.iter_child_nodes(tree):
        if isinstance(child, ast.Import | ast.ImportFrom):
            yield child, in_function
        yield from _walk(child, in_function or isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda))


def _violations(package: Path = PACKAGE) -> tuple[list[str], list[str]]:
    layering, nested = [], []
    for path, parts in _modules(package):
        is_package = path.name == "__init__.py"
        if is_package:
            parts = parts[:-1]
        unit = _unit(parts)
        rank = _rank(unit)
        tree = ast.parse(path.read_text(), filename=str(path))
        where = str(path.relative_to(package.parent))
        for node, in_function in _walk(tree):
            for target in _imported(node, parts, is_package):
                top = target[0]
                if in_function and top not in OPTIONAL:
                    nested.append(f"{where}:{node.lineno} imports {'.'.join(target)} inside a function")
                if top == "experiments":
                    layering.append(f"{where}:{node.lineno}: the library imports the research tree ({'.'.join(target)})")
                if top != "difffilter" or len(target) < 2:
                    continue
                other = target[1]
                if other == unit:
                    continue
                if _rank(other) > rank or (other in ABOVE_ALL_BUT_PAPERS and unit not in ABOVE_ALL_BUT_PAPERS):
                    layering.append(f"{where}:{node.lineno}: {unit} imports the higher floor {other} ({'.'.join(target)})")
    return layering, nested


def test_no_floor_imports_a_higher_one():
    layering, _ = _violations()
    assert not layering, "\n".join(layering)


def test_no_import_inside_a_function_body_except_optional_dependencies():
    _, nested = _violations()
    assert not nested, "\n".join(nested)


def _paper_crossings(papers: Path) -> list[str]:
    """Imports from one paper's package into another's (``experiments/papers/<paper>/``)."""
    out = []
    for path in sorted(papers.rglob("*.py")):
        parts = ["experiments", "papers", *path.relative_to(papers).with_suffix("").parts]
        is_package = path.name == "__init__.py"
        if is_package:
            parts = parts[:-1]
        if len(parts) < 3:
            continue
        for node, _ in _walk(ast.parse(path.read_text(), filename=str(path))):
            for target in _imported(node, parts, is_package):
                if target[:2] == ["experiments", "papers"] and len(target) > 2 and target[2] != parts[2]:
                    out.append(f"{path.relative_to(papers.parent)}:{node.lineno}: paper {parts[2]} imports paper {target[2]}")
    return out


def test_no_paper_imports_another():
    crossings = _paper_crossings(EXPERIMENTS / "papers")
    assert not crossings, "\n".join(crossings)


def test_no_paper_code_in_the_library():
    assert not (PACKAGE / "papers").exists() and not (PACKAGE / "bench").exists()
    offenders = [str(p.relative_to(ROOT)) for p in PACKAGE.rglob("*.py") if any(f"p00{i}" in p.name for i in range(5))]
    assert not offenders, offenders


def test_the_checker_sees_violations(tmp_path):
    # A fake tree with each kind of violation: the checker must report them (it is not vacuous).
    fake = tmp_path / "difffilter"
    for sub in ("models", "learn"):
        (fake / sub).mkdir(parents=True)
        (fake / sub / "__init__.py").write_text("")
    (fake / "__init__.py").write_text("")
    (fake / "models" / "__init__.py").write_text("from ..learn import data\n")
    (fake / "models" / "m.py").write_text("def f():\n    import torch\n    from scipy import stats\n")
    (fake / "learn" / "x.py").write_text("from experiments.papers.p001 import simulator\n")
    layering, nested = _violations(fake)
    assert any("models imports the higher floor learn" in v for v in layering), layering
    assert any("the library imports the research tree" in v for v in layering), layering
    assert [v for v in nested if "torch" in v] and not [v for v in nested if "scipy" in v], nested
    papers = tmp_path / "experiments" / "papers"
    for sub in ("p001", "p002"):
        (papers / sub).mkdir(parents=True)
        (papers / sub / "__init__.py").write_text("")
    (papers / "p002" / "x.py").write_text("from ..p001 import simulator\nfrom difffilter.learn import data\n")
    crossings = _paper_crossings(papers)
    assert len(crossings) == 1 and "paper p002 imports paper p001" in crossings[0], crossings


@pytest.mark.parametrize("script", sorted((ROOT / "experiments").glob("*.py")), ids=lambda p: p.name)
def test_entry_points_use_the_installed_package(script):
    text = script.read_text()
    tree = ast.parse(text)
    edits = [n for n in ast.walk(tree) if isinstance(n, ast.Attribute) and n.attr == "path" and getattr(n.value, "id", None) == "sys"]
    # The one allowed edit: the repository root first on sys.path, so that `experiments.*` (not
    # installed) imports; the library itself comes from the installed package.
    allowed = "sys.path.insert(0, str(Path(__file__).resolve().parents[1]))"
    if edits and (len(edits) != 1 or text.count(allowed) != 1):
        pytest.fail(f"{script.name} edits sys.path beyond the repository-root line: the library is installed (pip install -e .)")
    nested = [node.lineno for node, inside in _walk(tree) if inside]
    assert not nested, f"{script.name} imports inside a function (lines {nested})"
