"""The package's import promises (README, STYLE): Exudyn only in the ground-truth subpackage; the model,
reduction and observer never reach for it; the mechanism description imports nothing from the rest; the library
never imports the command line or the plots; imports run one way (no cycles, lazy imports inside functions
included) along the pipeline's layers."""

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "exuflex"


def _module_name(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules(sub: str = "") -> list[Path]:
    return sorted((PKG / sub).rglob("*.py"))


MODULES = {_module_name(p): p for p in _modules()}


def _imports(path: Path) -> set[str]:
    """Absolute module names imported anywhere in the file (lazy imports inside functions included).

    ``from P import name`` counts as an import of the module ``P.name`` where that is one of the package's
    modules (``from . import _compiled``), else of ``P`` (``from .basis import CraigBampton``)."""
    rel = path.relative_to(PKG.parent).with_suffix("").parts
    package = rel[:-1]  # a module's package (for __init__.py: the package itself)
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                mod = ".".join(base + ((node.module,) if node.module else ()))
            else:
                mod = node.module
            for a in node.names:
                out.add(f"{mod}.{a.name}" if f"{mod}.{a.name}" in MODULES else mod)
    return out


def _graph() -> dict[str, set[str]]:
    """Import edges between the package's own modules."""
    return {m: {i for i in _imports(p) if i in MODULES and i != m} for m, p in MODULES.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan): each holds an import cycle."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_exudyn_is_imported_by_the_ground_truth_subpackage_only():
    offenders = [p.relative_to(PKG) for p in _modules()
                 if any(m.split(".")[0] == "exudyn" for m in _imports(p)) and "groundtruth" not in p.parts]
    assert not offenders


def test_model_reduction_and_observer_never_import_the_ground_truth():
    for sub in ("erls", "reduction", "observer", "scoring"):
        for p in _modules(sub):
            bad = {m for m in _imports(p) if m.startswith(("exuflex.groundtruth", "exuflex.truth"))
                   or m.split(".")[0] == "exudyn"}
            assert not bad, (p.relative_to(PKG), bad)


def test_mechanism_imports_nothing_from_the_rest_of_the_package():
    for p in _modules("mechanism"):
        bad = {m for m in _imports(p) if m.startswith("exuflex.") and not m.startswith("exuflex.mechanism")}
        assert not bad, (p.relative_to(PKG), bad)


def test_the_library_never_imports_the_command_line_or_the_plots():
    front = ("exuflex.cli", "exuflex.__main__", "exuflex.plots")
    for m, p in MODULES.items():
        if m.startswith(front):
            continue
        bad = {i for i in _imports(p) if i.startswith(front)}
        assert not bad, (p.relative_to(PKG), bad)


def test_no_import_cycles_between_modules():
    assert _cycles(_graph()) == []


# The pipeline's layers (STYLE.md): a module imports only from its own layer's package or from lower layers.
LAYERS = (
    ("exuflex", "exuflex.data", "exuflex.mechanism"),
    ("exuflex.erls", "exuflex.probes"),
    ("exuflex.errors", "exuflex.manoeuvre", "exuflex.reduction", "exuflex.sensors", "exuflex.validate"),
    ("exuflex.groundtruth", "exuflex.measure", "exuflex.runs"),
    ("exuflex.observer", "exuflex._compile"),
    ("exuflex.scoring",),
    ("exuflex.truth",),
    ("exuflex.bench", "exuflex.study"),
    ("exuflex.plots",),
    ("exuflex.cli", "exuflex.__main__"),
)


def _unit(module: str) -> str:
    """The top-level module or subpackage a module belongs to (``exuflex.observer.ekf`` -> ``exuflex.observer``)."""
    return ".".join(module.split(".")[:2])


def _rank(module: str) -> int:
    for k, layer in enumerate(LAYERS):
        if _unit(module) in layer:
            return k
    raise AssertionError(f"{module}: not in any layer of test_imports.LAYERS; add it where it belongs")


def test_imports_run_down_the_pipeline_layers():
    for m, deps in _graph().items():
        for d in deps:
            if _unit(d) == _unit(m):
                continue
            assert _rank(d) <= _rank(m), f"{m} imports {d}, a module of a higher layer"


def test_the_import_parser_sees_relative_and_lazy_imports():
    found = _imports(PKG / "cli" / "modes.py")
    assert "exuflex.groundtruth" in found  # a lazy ``from ..groundtruth import ...`` inside a function
    assert "exuflex.reduction._compiled" in _imports(PKG / "reduction" / "basis.py")  # ``from . import _compiled``


@pytest.mark.parametrize("edges, expected", [
    ({"a": {"b"}, "b": {"c"}, "c": set()}, []),
    ({"a": {"b"}, "b": {"a"}, "c": {"a"}}, [["a", "b"]]),
    ({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"d"}}, [["a", "b", "c"]]),
])
def test_the_cycle_finder(edges, expected):
    assert _cycles(edges) == expected
