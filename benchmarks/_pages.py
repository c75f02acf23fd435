"""What the benchmarks that write a markdown page share: the page with its package versions, printed and written."""

from __future__ import annotations

import subprocess
from pathlib import Path


def _code_commit() -> str | None:
    """The commit of the checkout the imported ``exuflex`` comes from (an editable install may be another checkout
    than this script's), when the script started: its code measured the page; ``+changes`` if the package's
    files differ from it; None outside a git checkout."""
    import exuflex

    root = Path(exuflex.__file__).resolve().parents[1]
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--", "exuflex"],
                               capture_output=True, text=True, check=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None
    return head + (" +changes" if dirty else "")


COMMIT = _code_commit()  # at import: a long run's checkout may move on before the page is written


def publish(page: str, out: str | None) -> None:
    """Append the code's commit and the package versions to ``page``, print it and write it to ``out`` (None or
    '': not written)."""
    from exuflex.runs import versions_text

    page += (f"Code: commit {COMMIT}. " if COMMIT else "") + f"Versions: {versions_text()}.\n"
    print(page)
    if out:
        Path(out).write_text(page)


def rewrite_block(path: str | Path, begin: str, end: str, text: str) -> None:
    """Replace the page's block from the marker ``begin`` to ``end`` by ``text`` (which holds both markers),
    or append it if the page has none."""
    page = Path(path)
    old = page.read_text() if page.exists() else ""
    if begin in old and end in old:
        new = old[: old.index(begin)] + text + old[old.index(end) + len(end) :]
    else:
        new = old + ("\n" if old and not old.endswith("\n") else "") + text + "\n"
    page.write_text(new)
