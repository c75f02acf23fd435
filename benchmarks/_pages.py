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
