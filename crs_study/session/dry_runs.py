"""Dry-runs: many simulated participants on the simulated device and a virtual clock."""

from __future__ import annotations

import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

from crs_study.dataset.folder import Dataset, dataset_dir, is_simulated_label
from crs_study.errors import SessionError
from crs_study.paths import resolve_protocol
from crs_study.protocol import Protocol, load_protocol
from crs_study.protocol.lock import current_lock
from crs_study.session.runner import dataset_task, run_session
from crs_study.session.spec import DryRunResult, Progress, SessionResult, SessionSpec
from crs_study.signals import die_with_parent

#: The most simulated participants one dry-run takes (a study of this many sessions is
#: already hours of machine time; a larger number is a typo, and 2**31 labels exhaust memory).
MAX_PARTICIPANTS = 10_000


def check_participant_count(n: object) -> int:
    """``n`` simulated participants, 1 to :data:`MAX_PARTICIPANTS`, or a one-line
    :class:`SessionError` before any work."""
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_PARTICIPANTS:
        raise SessionError(f"--participants must be a whole number from 1 to "
                           f"{MAX_PARTICIPANTS}, got {n!r}")
    return n


def simulated_labels(n: int, prefix: str = "sim") -> list[str]:
    """``sim01`` .. ``simNN`` (at least two digits, so labels sort in order). The prefix
    must keep the labels in the simulated participants' label space
    (:func:`crs_study.dataset.is_simulated_label`): a dry-run never runs a person's label."""
    check_participant_count(n)
    if not is_simulated_label(f"{prefix}{n}"):
        raise SessionError(f"prefix {prefix!r}: simulated participants' labels begin with "
                           "'sim' (a person's never do)")
    width = max(2, len(str(n)))
    return [f"{prefix}{i:0{width}d}" for i in range(1, n + 1)]




def _dry_run_one(spec: SessionSpec) -> SessionResult:
    return run_session(spec)


def dry_run(protocol: str | os.PathLike[str] | Protocol, participants: int,
            out: str | os.PathLike[str], *, jobs: int = 1, responder: str = "observer",
            device_url: str = "sim://", prefix: str = "sim", progress: Progress | None = None,
            durable: bool = False) -> DryRunResult:
    """Session 1 of ``participants`` simulated participants on a virtual clock, stored in the
    dataset ``out``; returns the sessions' results (:class:`DryRunResult`).

    ``protocol`` is a protocol file, a shipped protocol's name (``"pilot"``) or a
    :class:`~crs_study.protocol.Protocol` object; one changed in Python
    (``dataclasses.replace``) is checked and settled once, before anything is written
    (:func:`~crs_study.protocol.load_protocol`), and each session stores the text it runs.

    Participant i (from 0) gets counterbalance index i, so the protocol's block orders are
    balanced across the N. With ``jobs > 1`` sessions run in that many worker processes (each
    session is written by one process; the dataset lock serialises ``participants.tsv``).
    Completed sessions already in the dataset are left as they are (a rerun resumes).
    ``durable=False`` (a documented choice; ``--fsync`` turns it off) fsyncs each session
    once, when it stops, rather than after every trial as ``crs-study run`` does: a killed
    dry-run still loses nothing and resumes exactly. A power cut costs at most the unfinished
    sessions; one whose files the cut left inconsistent is refused on resume in one line,
    and removing its files lets the same command regenerate it exactly from its seed.
    """
    if not device_url.startswith("sim://"):
        raise SessionError(f"a dry-run uses the simulated device (sim://...), got "
                           f"{device_url!r}; use crs-study run for a real device")
    if not isinstance(jobs, int) or jobs < 1:
        raise SessionError(f"--jobs must be a whole number >= 1, got {jobs!r}")
    if responder == "keypad":
        raise SessionError("a dry-run has no person at the keypad: use --responder observer, "
                           "random or scripted:FILE")
    labels = simulated_labels(participants, prefix)
    out = dataset_dir(out, "out")
    # a shipped protocol's name, or a path (each session loads it); an object is settled now
    protocol = load_protocol(protocol) if isinstance(protocol, Protocol) else \
        resolve_protocol(protocol)
    loaded = protocol if isinstance(protocol, Protocol) else \
        load_protocol(protocol, check_device=False)
    current_lock(loaded)  # a lock it no longer matches: refused before the folder is made
    Dataset(out, task=dataset_task(loaded.symbol_set)).ensure()  # its task names the files
    specs = [SessionSpec(protocol, label, Path(out), device_url, 1, responder,
                         "virtual", i, durable=durable) for i, label in enumerate(labels)]
    results: list[SessionResult] = []

    def note(result: SessionResult) -> None:
        results.append(result)
        if progress:
            progress(f"dry-run: {len(results)}/{len(specs)} participants "
                     f"(sub-{result.participant}: {result.status}, "
                     f"{result.trials_completed} trials)")

    if jobs == 1 or len(specs) == 1:
        for spec in specs:
            note(run_session(spec))
    else:
        context = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=min(jobs, len(specs)), mp_context=context,
                                 initializer=die_with_parent,
                                 initargs=(os.getpid(),)) as pool:
            futures = [pool.submit(_dry_run_one, spec) for spec in specs]
            try:
                for future in as_completed(futures):
                    note(future.result())
            except BaseException:
                for future in futures:
                    future.cancel()
                raise
    order = {label: i for i, label in enumerate(labels)}
    return DryRunResult(Path(out), tuple(sorted(results, key=lambda r: order[r.participant])))
