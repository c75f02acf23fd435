"""The documentation site builds with warnings as errors, and the README links only to pages that exist.

The build is a fresh one in a temporary folder with the gallery's scripts not run (``-D plot_gallery=0``);
``make -C docs html`` runs them. Two incremental rebuilds check that the build fails where it should: a page
missing from every toctree, and a docstring numpydoc cannot match to its function.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
GENERATED = ("_build", "auto_examples", "generated", "sg_execution_times.rst")


def _sphinx(src: Path, out: Path, extra_path: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=os.pathsep.join(
        str(p) for p in (ROOT, extra_path) if p is not None))
    cmd = [sys.executable, "-m", "sphinx", "-W", "--keep-going", "-q", "-b", "html", "-D", "plot_gallery=0",
           "-d", str(out / "doctrees"), str(src), str(out / "html")]
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600, check=False)


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    """A copy of docs/, examples/ and models/README.md (the schema page includes it), built once."""
    tmp = tmp_path_factory.mktemp("site")

    def ignore(folder, names):
        return [n for n in names if n in GENERATED or (Path(folder).name == "api" and n.startswith("exuflex"))
                or n == "__pycache__"]

    shutil.copytree(ROOT / "docs", tmp / "docs", ignore=ignore)
    shutil.copytree(ROOT / "examples", tmp / "examples", ignore=shutil.ignore_patterns("__pycache__", "data"))
    (tmp / "models").mkdir()
    shutil.copy(ROOT / "models" / "README.md", tmp / "models" / "README.md")
    res = _sphinx(tmp / "docs", tmp / "out")
    assert res.returncode == 0, f"sphinx-build -W failed:\n{res.stdout[-4000:]}\n{res.stderr[-8000:]}"
    return tmp


def test_site_builds_with_every_curated_name(site):
    import exuflex

    html = site / "out" / "html"
    assert (html / "index.html").exists()
    pages = {p.name for p in (html / "api" / "generated").glob("*.html")}
    missing = [n for n in exuflex._API if not any(p.endswith(f".{n}.html") for p in pages)]
    assert not missing, f"curated names without an API page: {missing}"


def test_build_fails_on_a_page_outside_every_toctree(site):
    """(A page at the root of docs/ is a benchmark page, listed by conf.py; one in a section must be placed.)"""
    page = site / "docs" / "tutorials" / "orphan_page.md"
    page.write_text("# A page no toctree lists\n")
    try:
        res = _sphinx(site / "docs", site / "out")
        assert res.returncode != 0
        assert "orphan_page" in res.stderr and "toctree" in res.stderr
    finally:
        page.unlink()


def test_build_fails_on_a_docstring_numpydoc_rejects(site, tmp_path):
    (tmp_path / "stale_doc.py").write_text(
        'def f(a):\n    """Summary.\n\n    Parameters\n    ----------\n    a : int\n        One.\n'
        '    b : int\n        A parameter the function no longer has.\n    """\n')
    page = site / "docs" / "api" / "index.rst"
    text = page.read_text()
    page.write_text(text + "\n.. autofunction:: stale_doc.f\n")
    try:
        res = _sphinx(site / "docs", site / "out", extra_path=tmp_path)
        assert res.returncode != 0
        assert "PR02" in res.stderr, res.stderr[-3000:]
    finally:
        page.write_text(text)


def test_theory_pages_link_to_the_code(site):
    """Every code object a theory page names by role ({py:class}, {py:func}) resolves to its API page: an
    unresolved role renders as plain code without a warning, so a renamed function would leave a dead name."""
    bad = {}
    for page in sorted((site / "out" / "html" / "theory").glob("*.html")):
        html = page.read_text()
        refs = re.findall(r'(<a [^>]*>)?<code class="xref py[^"]*"><span class="pre">([^<]*)</span>', html)
        dead = [name for link, name in refs if not link]
        if dead:
            bad[page.name] = dead
    assert not bad, f"theory pages name code objects that have no API page: {bad}"
    index = (site / "out" / "html" / "theory" / "index.html").read_text()
    assert "exuflex.erls.model.ErlsModel.html" in index  # the equation table links eq. 2 to its class


def _readme_links() -> list[str]:
    text = (ROOT / "README.md").read_text()
    return re.findall(r"\]\(([^)\s]+)\)", text)


def test_readme_links_exist(site):
    """Every relative link of the README names a file of the repository or a page of the built site."""
    html = site / "out" / "html"
    bad = []
    for link in _readme_links():
        if re.match(r"^[a-z]+://", link) or link.startswith("#"):
            continue
        target = link.split("#")[0]
        if target.startswith("docs/") and target.endswith(".html"):  # a page of the site: built from a source
            ok = (html / target[len("docs/"):]).exists()
        else:
            ok = (ROOT / target).exists()
        if not ok:
            bad.append(link)
    assert not bad, f"README links to missing pages: {bad}"


def test_readme_python_example_runs():
    """The README's Python example runs as written, from the repository's root, and prints a ratio per quantity."""
    text = (ROOT / "README.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, re.DOTALL)
    assert blocks, "the README has no Python example"
    code = blocks[0]
    assert len(code.strip().splitlines()) <= 12, "the README's example should stay about 10 lines"
    env = dict(os.environ, MPLBACKEND="Agg", PYTHONPATH=str(ROOT))
    res = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True, check=False,
                         timeout=600)
    assert res.returncode == 0, res.stderr[-3000:]
    rows = [line.split() for line in res.stdout.strip().splitlines()]
    assert rows and all(len(r) == 2 and float(r[1]) > 0 for r in rows), res.stdout
    assert {"q1", "q2", "q3"} <= {r[0] for r in rows}


def test_readme_test_command_is_ci_s():
    """The README's test command and install line are the ones .ci/run runs."""
    ci = (ROOT / ".ci" / "run").read_text()
    readme = (ROOT / "README.md").read_text()
    install = re.search(r'^python -m pip install -e "(\.\[[^\]]*\])"$', ci, re.MULTILINE).group(1)
    assert f'python -m pip install -e "{install}"' in readme
    test_cmd = [ln for ln in ci.splitlines() if ln.startswith("python -m pytest")][-1]
    assert any(ln.startswith(test_cmd + " ") or ln == test_cmd for ln in readme.splitlines())


def test_every_model_has_a_gallery_page():
    """The gallery shows every mechanism of models/: a script of its own (examples/plot_<name>.py, which runs
    that file) or, for a model file added without one, examples/plot_more_mechanisms.py, which draws every model
    file that has no script."""
    assert (ROOT / "examples" / "plot_more_mechanisms.py").exists()
    bad = []
    for model in sorted((ROOT / "models").glob("*.toml")):
        script = ROOT / "examples" / f"plot_{model.stem}.py"
        if script.exists() and f'"{model.stem}"' not in script.read_text():
            bad.append(model.name)
    assert not bad, f"gallery scripts that do not load their model file: {bad}"
