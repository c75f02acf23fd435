"""The package's import promises (README, STYLE): Exudyn only in the ground-truth subpackage; the model,
reduction and observer never reach for it; the mechanism description imports nothing from the rest."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "exuflex"


def _imports(path: Path) -> set[str]:
    """Absolute module names imported anywhere in the file (lazy imports inside functions included)."""
    rel = path.relative_to(PKG.parent).with_suffix("").parts
    package = rel[:-1]  # a module's package (for __init__.py: the package itself)
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                out.add(".".join(base + ((node.module,) if node.module else ())))
            else:
                out.add(node.module)
    return out


def _modules(sub: str = "") -> list[Path]:
    return sorted((PKG / sub).rglob("*.py"))


def test_exudyn_is_imported_by_the_ground_truth_subpackage_only():
    offenders = [p.relative_to(PKG) for p in _modules()
                 if any(m.split(".")[0] == "exudyn" for m in _imports(p)) and "groundtruth" not in p.parts]
    assert not offenders


def test_model_reduction_and_observer_never_import_the_ground_truth():
    for sub in ("erls", "reduction", "observer"):
        for p in _modules(sub):
            bad = {m for m in _imports(p) if m.startswith("exuflex.groundtruth") or m.split(".")[0] == "exudyn"}
            assert not bad, (p.relative_to(PKG), bad)


def test_mechanism_imports_nothing_from_the_rest_of_the_package():
    for p in _modules("mechanism"):
        bad = {m for m in _imports(p) if m.startswith("exuflex.") and not m.startswith("exuflex.mechanism")}
        assert not bad, (p.relative_to(PKG), bad)


def test_the_import_parser_sees_relative_and_lazy_imports():
    found = _imports(PKG / "cli" / "modes.py")
    assert "exuflex.groundtruth" in found  # a lazy ``from ..groundtruth import ...`` inside a function
