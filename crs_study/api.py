"""The functions of the Python API that join stages (``crs_study`` re-exports them).

The rest of the API is the stages' own functions, re-exported as they are by
:mod:`crs_study`: :func:`~crs_study.protocol.load_protocol`, :func:`~crs_study.session.dry_run`,
:func:`~crs_study.analysis.load_dataset` and :func:`~crs_study.analysis.analyze`. Here:

* :func:`make_plan`: one participant's trial plan, from any protocol source;
* :func:`validate`: a protocol checked, and its plan summarised (what ``crs-study validate``
  prints) as a :class:`ProtocolSummary`;
* :func:`run_session`: one participant's session, begun or resumed, from keyword arguments
  (``crs-study run``; :func:`crs_study.session.run_session` takes a
  :class:`~crs_study.session.SessionSpec`).

Every function takes a protocol as a file, a shipped protocol's name or a
:class:`~crs_study.protocol.Protocol` object (one changed with :func:`dataclasses.replace`
runs as :func:`~crs_study.protocol.load_protocol` settles it).
"""

from __future__ import annotations

import os
from pathlib import Path

from crs_study.errors import ProtocolError, ProtocolProblems
from crs_study.protocol import Protocol, TrialPlan, load_protocol
from crs_study.protocol import make_plan as plan_of
from crs_study.protocol.problems import protocol_problems
from crs_study.protocol.summary import (  # noqa: F401  (re-exported: the API's names)
    SUMMARY_COLUMNS,
    ProtocolSummary,
    adaptive_summary,
    summarise,
)
from crs_study.session import SessionResult, SessionSpec
from crs_study.session import run_session as run_spec
from crs_study.session.spec import Progress

ProtocolSource = str | os.PathLike[str] | Protocol

def make_plan(protocol: ProtocolSource, participant: str, session: int = 1,
              counterbalance: int = 0) -> TrialPlan:
    """The trial plan of ``participant``'s ``session`` at counterbalance index
    ``counterbalance`` (the order of arrival from 0), as a run of ``protocol`` plays it
    (deterministic: :mod:`crs_study.protocol.plan`)."""
    return plan_of(load_protocol(protocol), participant, session, counterbalance)


def validate(protocol: ProtocolSource, *, participant: str = "example", session: int = 1,
             counterbalance: int = 0) -> ProtocolSummary:
    """Check a protocol strictly (every key, then against its device) and summarise the plan
    of ``participant``: trials, blocks and their orders, expected duration, frames, wire use.

    Raises :class:`~crs_study.errors.ProtocolError` (one line: file, line, key, value) for
    a protocol with one problem, and :class:`~crs_study.errors.ProtocolProblems` (one line
    each) listing every problem one reading finds
    (:func:`~crs_study.protocol.problems.protocol_problems`) when there are more.
    """
    try:
        checked = load_protocol(protocol)
    except ProtocolError as first:
        problems = protocol_problems(protocol)
        if len(problems) > 1:
            raise ProtocolProblems(problems) from None
        raise first from None
    plan = plan_of(checked, participant, session, counterbalance)
    return summarise(checked, plan, participant, session, counterbalance)


def run_session(protocol: ProtocolSource, participant: str, out: str | os.PathLike[str], *,
                device_url: str = "sim://", session: int = 1, responder: str = "keypad",
                clock: str = "auto", counterbalance: int | None = None,
                consent_register: str | os.PathLike[str] | None = None,
                progress: Progress | None = None) -> SessionResult:
    """Run (or resume) one participant's session and store it in the dataset ``out``.

    Parameters
    ----------
    protocol : a protocol file, a shipped protocol's name or a ``Protocol`` object.
    participant : the participant's label (letters and digits; never a name).
    out : the dataset folder (BIDS); made when missing.
    device_url : ``sim://[?options]`` or ``serial:///dev/ttyUSB0,/dev/ttyUSB1``.
    session : the session number (a completed session is never rewritten).
    responder : ``keypad`` (a person at the terminal), ``scripted:FILE``, ``observer`` or
        ``random`` (simulated participants).
    clock : ``real``, ``virtual`` or ``auto`` (virtual for ``sim://`` with a simulated
        responder).
    counterbalance : the counterbalance index (default: the order of arrival).
    consent_register : the consent register: a person's label needs a consent record on
        every device, ``sim://`` included (only a ``sim...`` label with a simulated
        responder on ``sim://`` needs none).
    progress : called with one line of progress at a time.

    Returns
    -------
    SessionResult
        ``status`` ``complete``, ``interrupted`` (Ctrl-C: run again to resume) or
        ``already-complete``.
    """
    spec = SessionSpec(protocol, participant, Path(out), device_url, session, responder, clock,
                       counterbalance, None if consent_register is None
                       else Path(consent_register))
    return run_spec(spec, progress=progress)
