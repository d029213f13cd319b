"""The package is the product: it never imports the experiments (research/, results/), and every module in it is
reached from its entry points (the `trivla-drake` command, `python -m` runners) or its public API, so nothing in it
is an orphan that only an experiment or a test uses."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "trivla_drake"
# Where users come in: the console script (pyproject's [project.scripts]), the public API of `trivla_drake`
# (its lazily imported names) and the modules run with `python -m` (torchrun runs train/cli_commands).
ENTRY_MODULES = ("trivla_drake", "trivla_drake.cli", "trivla_drake.train.cli_commands",
                 "trivla_drake.eval.cli_commands")
# Modules kept for users though no entry point imports them, each with why.
NOT_IMPORTED_BY_DESIGN = {
    "trivla_drake.train.synthetic": "writes the small synthetic LeRobot dataset the tests and a first `train` try use",
}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


def _imports(name: str) -> set[str]:
    """Every module `name` imports, at its top or inside functions (lazy imports count), and the module names its
    text spells out as strings (the public API's table, `python -m` targets)."""
    path = MODULES[name]
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + ([base] if base else []))
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in MODULES:
            found.add(node.value)
    return found


def test_the_package_never_imports_the_experiments():
    for name in MODULES:
        experiments = sorted(m for m in _imports(name) if m.split(".")[0] in ("research", "results"))
        assert not experiments, f"{MODULES[name]} imports {experiments}: the package reaches research/ never"


def test_every_module_is_reached_from_the_entry_points_or_the_public_api():
    reached, todo = set(), list(ENTRY_MODULES)
    while todo:
        name = todo.pop()
        if name in reached or name not in MODULES:
            continue
        reached.add(name)
        for imported in _imports(name):
            parts = imported.split(".")
            todo.extend(".".join(parts[:i]) for i in range(1, len(parts) + 1))  # a module's packages run too
    orphans = sorted(set(MODULES) - reached - set(NOT_IMPORTED_BY_DESIGN))
    assert not orphans, f"modules nothing of the product imports (move them to research/ or delete them): {orphans}"


@pytest.mark.parametrize("source, expected", [
    ("from trivla_drake.eval import episode\n", {"trivla_drake.eval", "trivla_drake.eval.episode"}),
    ("def f():\n    import results.x\n", {"results.x"}),
])
def test_the_import_scan_sees_lazy_and_package_imports(tmp_path, monkeypatch, source, expected):
    """The scan would catch what it looks for: imports inside functions and `from package import module`."""
    path = tmp_path / "probe_module.py"
    path.write_text(source)
    monkeypatch.setitem(MODULES, "trivla_drake.probe_module", path)
    assert expected <= _imports("trivla_drake.probe_module")
