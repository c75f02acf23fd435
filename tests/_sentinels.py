"""Sentinels for tests of the checks before work: each command's work replaced by :class:`Reached`, so that a case
that passes every check costs milliseconds (the computations are tested elsewhere)."""

from __future__ import annotations


class Reached(BaseException):
    """The checks passed: the work would start here."""


def reach(*a, **k):
    raise Reached


def stop_work(monkeypatch) -> None:
    """Replace the first step of every command's work (the manoeuvre's plan, the observer's construction, the study's
    settings, reproduce's body, the reduced modes report, the design's observer) by :func:`reach`."""
    import exuflex.cli.reproduce
    import exuflex.manoeuvre
    import exuflex.scoring.design
    import exuflex.observer.session as session
    import exuflex.reduction
    from exuflex.study.runner import StudySpec

    monkeypatch.setattr(exuflex.manoeuvre, "plan", reach)
    monkeypatch.setattr(session, "make_observer", reach)
    monkeypatch.setattr(StudySpec, "settings", reach)
    monkeypatch.setattr(exuflex.cli.reproduce, "_reproduce", reach)
    monkeypatch.setattr(exuflex.reduction, "reduced_modes_report", reach)
    monkeypatch.setattr(exuflex.scoring.design, "make_observer", reach)
