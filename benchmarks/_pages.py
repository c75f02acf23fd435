"""What the benchmarks that write a markdown page share: the page with its package versions, printed and written."""

from __future__ import annotations

from pathlib import Path


def publish(page: str, out: str | None) -> None:
    """Append the package versions to ``page``, print it and write it to ``out`` (None or '': not written)."""
    from exuflex.runs import versions_text

    page += f"Versions: {versions_text()}.\n"
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
