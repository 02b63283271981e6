"""The package's floors (docs/architecture.md): a module may import only from its own floor or the
floors below, no import hides inside a function body (except optional dependencies), and the
Hydra entry points import the installed package instead of editing ``sys.path``.

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
    {"_util", "constraints", "geometry", "linalg", "params", "selection"},
    {"datasets"},  # file formats and the data-set registry: numpy only, below every model
    {"models"},
    {"filters"},
    {"mixers"},
    {"smoothers"},
    {"sim"},
    {"learn"},
    {"papers"},
]
#: Units that may import every floor below ``papers`` (the package root re-exports, the
#: benchmark measures).
ABOVE_ALL_BUT_PAPERS = {"__init__", "bench"}
#: Third-party packages that are optional (extras ``test``/``bench``): importing them lazily,
#: inside the function that needs them, is how their absence stays harmless.
OPTIONAL = {"dynamax", "filterpy", "jax", "mpmath", "scipy"}


def _rank(unit: str) -> float:
    for i, floor in enumerate(FLOORS):
        if unit in floor:
            return float(i)
    if unit in ABOVE_ALL_BUT_PAPERS:
        return len(FLOORS) - 1.5  # above learn, below papers
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
                if top != "difffilter" or len(target) < 2:
                    continue
                other = target[1]
                if other == unit:
                    if unit == "papers" and len(parts) > 2 and len(target) > 2 and target[2] != parts[2]:
                        layering.append(f"{where}:{node.lineno}: paper {parts[2]} imports paper {target[2]}")
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


def test_the_checker_sees_violations(tmp_path):
    # A fake package with each kind of violation: the checker must report them (it is not vacuous).
    fake = tmp_path / "difffilter"
    for sub in ("models", "learn", "papers/p001", "papers/p002"):
        (fake / sub).mkdir(parents=True)
        (fake / sub / "__init__.py").write_text("")
    (fake / "__init__.py").write_text("")
    (fake / "models" / "__init__.py").write_text("from ..learn import data\n")
    (fake / "models" / "m.py").write_text("def f():\n    import torch\n    from scipy import stats\n")
    (fake / "papers" / "p002" / "x.py").write_text("from ..p001 import simulator\nfrom ...learn import data\n")
    layering, nested = _violations(fake)
    assert any("paper p002 imports paper p001" in v for v in layering), layering
    assert not any("papers imports the higher floor" in v for v in layering), layering
    assert any("models imports the higher floor learn" in v for v in layering), layering
    assert [v for v in nested if "torch" in v] and not [v for v in nested if "scipy" in v], nested


@pytest.mark.parametrize("script", sorted((ROOT / "experiments").glob("*.py")), ids=lambda p: p.name)
def test_entry_points_use_the_installed_package(script):
    tree = ast.parse(script.read_text())
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr == "path" and isinstance(node.value, ast.Name) and node.value.id == "sys":
            pytest.fail(f"{script.name} edits sys.path: the package is installed (pip install -e .)")
    nested = [node.lineno for node, inside in _walk(tree) if inside]
    assert not nested, f"{script.name} imports inside a function (lines {nested})"
