"""Sphinx configuration of the exuflex site.

Build: ``pip install -e ".[docs]"`` then ``sphinx-build -W docs docs/_build/html`` (or ``make -C docs html``).
Warnings are errors. The gallery (``examples/``) runs at build time; ``-D plot_gallery=0`` builds it without
running the scripts (the test suite does that: ``tests/test_docs.py``).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if (ROOT / "exuflex").is_dir():
    sys.path.insert(0, str(ROOT))  # document the checkout being built, not another installed copy
os.environ.setdefault("MPLBACKEND", "Agg")

sys.path.insert(0, str(Path(__file__).resolve().parent / "_ext"))
sys.path.insert(0, str(ROOT / "examples"))  # the gallery's scripts import examples/_whole_chain.py
import exuflex  # noqa: E402  (after the path is set)

project = "exuflex"
author = "the exuflex developers"
copyright = "exuflex developers"
version = release = exuflex.__version__

extensions = [
    "sphinx.ext.autodoc",
    "sphinx.ext.autosummary",
    "sphinx.ext.mathjax",
    "numpydoc",
    "myst_parser",
    "sphinx_gallery.gen_gallery",
]

source_suffix = {".rst": "restructuredtext", ".md": "markdown"}
root_doc = "index"
exclude_patterns = ["_build", "**.ipynb_checkpoints", "auto_examples/*.ipynb", "auto_examples/*.py",
                    "auto_examples/*.zip", "auto_examples/*.json", "auto_examples/*.md5"]
templates_path = ["_templates"]

# ---------------------------------------------------------------- markdown (the existing docs/*.md pages)
myst_enable_extensions = ["dollarmath", "amsmath", "colon_fence", "deflist"]
myst_heading_anchors = 3
# A code block whose language Pygments cannot lex as written (e.g. JSON with comments in run_format.md) is
# highlighted in relaxed mode; that is not an error of the page.
# The benchmark pages are written by scripts (benchmarks/*.py); a heading level they skip (H2 to H4) is their style,
# not a defect of the site.
suppress_warnings = ["misc.highlighting_failure", "myst.header"]
# The benchmark pages are written by scripts in benchmarks/ and name their files in backticks; they are
# included as they are.

# ---------------------------------------------------------------- API reference
autosummary_generate = True
autosummary_imported_members = True
autodoc_default_options = {"members": False}
autodoc_typehints = "none"  # numpydoc's Parameters sections carry the types
numpydoc_show_class_members = False
numpydoc_class_members_toctree = False
numpydoc_xref_param_type = False
# numpydoc validation, narrowly: the checks that catch a docstring that no longer matches its function or
# that numpydoc cannot parse as written. (Checks on style, e.g. every parameter documented or a summary that
# ends with a period, are not enabled: many internal helpers document their parameters in prose.)
numpydoc_validation_checks = {"GL06", "GL07", "PR02", "PR10"}

# ---------------------------------------------------------------- gallery
sphinx_gallery_conf = {
    "examples_dirs": str(ROOT / "examples"),
    "gallery_dirs": "auto_examples",
    "filename_pattern": r"/plot_",  # executed at build time; the other examples are shown, not run
    "ignore_pattern": r"__init__\.py|/data/|(^|/)_[^/]*\.py$",  # _whole_chain.py: a module the scripts import
    "within_subsection_order": "exuflex_figures.GalleryOrder",  # _ext/exuflex_figures.py
    "download_all_examples": False,
    "remove_config_comments": True,
    "abort_on_example_error": True,
    "image_scrapers": ("matplotlib", "exuflex_figures"),  # _ext/exuflex_figures.py: the files in FIGURES
    "matplotlib_animations": False,
    "show_memory": False,
}

# ---------------------------------------------------------------- HTML
html_theme = "pydata_sphinx_theme"
html_title = f"exuflex {release}"
html_static_path = ["_static"]
html_theme_options = {
    "navigation_with_keys": False,
    "header_links_before_dropdown": 6,
    "show_toc_level": 2,
    "secondary_sidebar_items": ["page-toc"],
    "footer_start": ["copyright"],
    "footer_end": ["sphinx-version", "theme-version"],
}
html_show_sourcelink = False
html_css_files = ["custom.css"]
html_sidebars = {"index": [], "getting_started": []}  # single pages: no section navigation
html_context = {"default_mode": "light"}


# ---------------------------------------------------------------- API pages from the code's own lists
# The curated namespace (``exuflex._API``) and each stage's ``__all__``: every public function and class gets
# an autosummary page, so a name added to the code appears here without editing the site.
API_MODULES = [
    ("exuflex.mechanism", "Model files: the mechanism as frozen data"),
    ("exuflex.erls.model", "The full-order ERLS model (eq. 2)"),
    ("exuflex.erls.modal", "Modes of the full-order model"),
    ("exuflex.erls.implicit", "The ERLS truth's integrator and the truth step rule"),
    ("exuflex.erls.simulate", "Explicit integration of the full-order model (RK4)"),
    ("exuflex.erls.validity", "Where the ERLS model stops being valid"),
    ("exuflex.reduction", "Craig-Bampton reduction (eqs. 3-7, 16-17)"),
    ("exuflex.reduction.static", "Static corrections of the reduced basis"),
    ("exuflex.reduction.truncation", "The interior modes' filter requirement"),
    ("exuflex.observer", "The observer: EKF, estimators (eqs. 8-15)"),
    ("exuflex.observer.reduced", "The reduced model as the filter's discrete-time model (eqs. 8-9)"),
    ("exuflex.observer.kalman", "The Kalman algebra (eqs. 10-15)"),
    ("exuflex.scoring", "Scoring an observer: errors against a truth, the estimation bound"),
    ("exuflex.scoring.bound", "The estimation bound"),
    ("exuflex.groundtruth", "The Exudyn truth"),
    ("exuflex.truth", "Truth engines and run simulation"),
    ("exuflex.manoeuvre", "Manoeuvre planning and computed torque"),
    ("exuflex.sensors", "Signals and sensor channels"),
    ("exuflex.measure", "Measurement noise and quantisation"),
    ("exuflex.runs", "Run folders and lab logs"),
    ("exuflex.validate", "Checks of mechanisms, logs and settings"),
    ("exuflex.errors", "Errors"),
    ("exuflex.study", "Studies: payload and sweeps"),
    ("exuflex.plots", "Figures"),
    ("exuflex.bench", "Speed measurement"),
]


def _public(module_name: str) -> list[tuple[str, object]]:
    import importlib
    import inspect

    mod = importlib.import_module(module_name)
    out = []
    for name in getattr(mod, "__all__", []):
        obj = getattr(mod, name, None)
        if inspect.isclass(obj) or inspect.isfunction(obj) or callable(getattr(obj, "py_func", None)):
            out.append((name, obj))
    return sorted(out, key=lambda item: item[0].lower())


def _write_if_changed(path: Path, text: str) -> None:
    if not path.exists() or path.read_text() != text:
        path.write_text(text)


def _autosummary(names: list[str], toctree: bool) -> list[str]:
    if not names:
        return []
    head = [".. autosummary::"] + (["   :toctree: generated/"] if toctree else [])
    return head + [""] + [f"   {n}" for n in names] + [""]


def _api_pages(app, config=None) -> None:
    """Write ``api/<module>.rst`` for each stage and ``api/exuflex.rst`` for the curated namespace.

    Each object gets one page, under the first stage (in ``API_MODULES`` order) that exports it; other lists
    that hold it link to that page.
    """
    api = Path(app.srcdir) / "api"
    home: dict[int, str] = {}
    pages = {}
    for mod, title in API_MODULES:
        own, elsewhere = [], []
        for name, obj in _public(mod):
            if id(obj) in home:
                elsewhere.append(f"~{home[id(obj)]}")
            else:
                home[id(obj)] = f"{mod}.{name}"
                own.append(name)
        pages[mod] = (title, own, elsewhere)
    for mod, (title, own, elsewhere) in pages.items():
        head = f"``{mod}``: {title}"
        lines = [head, "=" * len(head), "", f".. automodule:: {mod}", "   :no-members:", "   :no-index:", "",
                 f".. currentmodule:: {mod}", ""]
        lines += _autosummary(own, True)
        if elsewhere:
            lines += ["Also exported here, documented with their stage:", ""] + _autosummary(elsewhere, False)
        _write_if_changed(api / f"{mod}.rst", "\n".join(lines))
    curated = []
    for name in sorted(exuflex._API, key=str.lower):
        obj = getattr(exuflex, name)
        if id(obj) not in home:  # a curated name no stage exports: documented here
            home[id(obj)] = f"exuflex.{name}"
            curated.append(f"~exuflex.{name}")
        else:
            curated.append(f"~{home[id(obj)]}")
    title = "The curated namespace: ``import exuflex as xf``"
    lines = [title, "=" * len(title), "",
             "The names a user needs, in one namespace (``xf.load_mechanism``, ``xf.make_observer``, ...). Each",
             "is imported from its stage when first used, so ``import exuflex`` stays light; each is",
             "documented on its stage's page, linked from the table.", ""]
    lines += _autosummary(curated, True)
    _write_if_changed(api / "exuflex.rst", "\n".join(lines))


# Pages at the root of docs/ that a section places by name; every other root page is a benchmark page (written by
# a script in benchmarks/) and is listed under "Benchmarks and results" without editing the site.
PLACED = {"index", "getting_started", "tuning", "validity", "run_format", "robustness"}


def _benchmark_pages(app, config=None) -> None:
    src = Path(app.srcdir)
    pages = sorted(p.stem for p in src.glob("*.md") if p.stem not in PLACED)
    lines = ["```{toctree}", ":maxdepth: 1", ""] + [f"/{p}" for p in pages] + ["```", ""]
    _write_if_changed(src / "results" / "benchmark_pages.txt", "\n".join(lines))


def setup(app):
    app.connect("config-inited", _api_pages)
    app.connect("config-inited", _benchmark_pages)
