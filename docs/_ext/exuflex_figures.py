"""A sphinx-gallery image scraper for the figures exuflex writes to files.

exuflex draws its figures with the library's own writers (:mod:`exuflex.plots`: ``modes_figure``,
``observer_figures``, ...), which save PNG files as ``exuflex observe --out`` does rather than leaving pyplot
figures open. A gallery script names the files a code block wrote in a global ``FIGURES`` (a list of paths,
as those writers return them); this scraper copies them into the gallery after the block and empties the list.
Open pyplot figures are collected by sphinx-gallery's own matplotlib scraper, listed beside this one.
"""

from __future__ import annotations

import shutil
from pathlib import Path


def figure_files_scraper(block, block_vars, gallery_conf, **kwargs) -> str:
    from sphinx_gallery.scrapers import figure_rst

    globs = block_vars.get("example_globals", {})
    files = [Path(p) for p in (globs.get("FIGURES") or [])]
    if not files:
        return ""
    written = []
    for src, dst in zip(files, block_vars["image_path_iterator"]):
        shutil.copyfile(src, dst)
        written.append(dst)
    globs["FIGURES"] = []
    return figure_rst(written, gallery_conf["src_dir"])


def _get_sg_image_scraper():
    return figure_files_scraper
