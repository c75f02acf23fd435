"""Package data: the paper's reported numbers (``paper_reference.json``), read with importlib.resources."""

from __future__ import annotations

import json
from functools import cache
from importlib import resources

__all__ = ["paper_reference"]


@cache
def _load() -> str:
    return resources.files(__name__).joinpath("paper_reference.json").read_text(encoding="utf-8")


def paper_reference() -> dict:
    """The numbers reported by Palomba et al. (2018), each entry with its ``source`` (table, figure or section).

    Returns
    -------
    dict
        A fresh copy on every call (callers may modify it). Keys include ``table2_reduced_model_accuracy``
        (``frequencies_hz``, ``nco``, ``frequency_error_pct``), ``table1_lumped_masses``,
        ``table3_noise_std``, ``fig4_torque_axes``, ``fig11_payload_study`` and, kept apart as not the
        paper's own, ``exuflex_reference`` (the team's reconstruction targets, e.g. the filter RMS bound).
    """
    return json.loads(_load())
