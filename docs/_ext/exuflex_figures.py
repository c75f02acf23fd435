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


#: The gallery's order: the paper's case, then the mechanisms from the simplest, then the examples a user starts
#: from. A script not listed comes after these, by file name.
ORDER = ["plot_sixbar.py", "plot_paper_reproduction.py", "plot_single_link.py", "plot_fourbar.py",
         "plot_slider_crank.py", "plot_l_arm.py", "plot_serial_arm.py", "plot_three_link_arm.py", "plot_fivebar.py",
         "plot_spin_up.py",
         "own_mechanism.py", "own_lab_log.py", "online_loop.py", "plot_more_mechanisms.py"]


class GalleryOrder:
    """``within_subsection_order`` for sphinx-gallery: :data:`ORDER`, then the other scripts by name."""

    def __init__(self, src_dir):
        self.src_dir = src_dir

    def __call__(self, filename: str):
        name = Path(filename).name
        return (ORDER.index(name), "") if name in ORDER else (len(ORDER), name)

    def __repr__(self):
        return "GalleryOrder"
