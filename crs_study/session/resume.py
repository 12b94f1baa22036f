"""Resume checks: a stored session continues only as the run that began it would have.

A session's sidecar records fingerprints (``FINGERPRINTS`` of
:mod:`crs_study.dataset.session_metadata`): the protocol file's sha256, the seed, the
counterbalance index, the trial plan's sha256, the device file's sha256 and the sha256 of every
bump path the protocol draws. A resume recomputes them and refuses, in one line naming what
differs, a session whose files or software would now play another plan (:func:`check_resume`);
it also refuses to finish a session by another kind of run than the one that began it
(:func:`check_same_kind_of_run`), stored rows that do not belong to the plan
(:func:`check_rows`), and stored frames that this software would render otherwise
(:func:`check_frames`).
"""

from __future__ import annotations

import hashlib
import tomllib
from pathlib import Path

import numpy as np

from crs_study._files import sha256_bytes
from crs_study.dataset.session_metadata import FINGERPRINTS, SessionMetadata
from crs_study.dataset.session_store import read_frame_log
from crs_study.errors import SessionError
from crs_study.geometry.layout import Layout
from crs_study.protocol.model import Protocol
from crs_study.protocol.plan import TrialPlan
from crs_study.session.spec import SessionSpec
from crs_study.stimuli.stimulus import make_stimulus

#: Fingerprint key (as in the sidecar) -> value, as :func:`fingerprints` computes them.
Fingerprints = dict[str, str | int]


def plan_sha256(plan: TrialPlan) -> str:
    """The plan's fingerprint (:meth:`~crs_study.protocol.plan.TrialPlan.sha256`)."""
    return plan.sha256()


def stimulus_sha256(protocol: Protocol, layout: Layout) -> str:
    """sha256 of every bump path the protocol shows on ``layout`` (each symbol at each level:
    frame times, centres, heights, diameter, and the symbol's ``repr``), so a resume under
    software that draws the symbols differently (another strokes scaling, say) is refused
    although the protocol file is unchanged. The digit set's symbols are ints, so digit
    protocols keep the fingerprints stored before stimulus sets existed."""
    digest = hashlib.sha256()
    for level in protocol.level_values:
        for symbol in protocol.symbols:
            stimulus = make_stimulus(protocol, layout, symbol, level)
            for array in (stimulus.frame_times, stimulus.centres_mm, stimulus.heights_mm):
                digest.update(np.ascontiguousarray(array, dtype="<f8").tobytes())
            digest.update(repr((symbol, level, float(stimulus.diameter_mm))).encode())
    return digest.hexdigest()


def fingerprints(protocol: Protocol, plan: TrialPlan, device_text: str,
                 layout: Layout) -> Fingerprints:
    """What a stored session must match to be resumed (see :func:`check_resume`)."""
    return {
        "ProtocolSha256": protocol.sha256, "Seed": int(plan.seed),
        "Counterbalance": int(plan.counterbalance), "PlanSha256": plan_sha256(plan),
        "DeviceFileSha256": sha256_bytes(device_text.encode("utf-8")),
        "StimulusSha256": stimulus_sha256(protocol, layout),
    }


def check_resume(stored: SessionMetadata, expected: Fingerprints, sidecar: Path,
                 device_text: str | None = None) -> None:
    """A stored session may only be resumed with the same plan: one line saying what differs.

    A fingerprint the stored session lacks (``StimulusSha256`` of a session begun by older
    software) is not compared. A device file whose text differs only in its comments or
    layout (``device_text`` reads as the same TOML as the stored text) is the same device.
    """
    recorded = stored.fingerprints()
    for key, label in FINGERPRINTS.items():
        if key == "DeviceFileSha256" and device_text is not None \
                and _same_toml(stored.device_file_text, device_text):
            continue
        if recorded[key] is not None and recorded[key] != expected[key]:
            raise SessionError(
                f"{sidecar}: cannot resume: the {label} differs ({key} stored "
                f"{recorded[key]!r}, now {expected[key]!r}); use the original files or start "
                "another --session")


def device_kind(url: str) -> str:
    """``"simulated"`` for ``sim://`` URLs, else ``"real"``."""
    return "simulated" if url.startswith("sim://") else "real"


def check_same_kind_of_run(stored: SessionMetadata, spec: SessionSpec, responder_name: str,
                           clock_kind: str, sidecar: Path) -> None:
    """A session is finished as it began: by the same kind of responder, on the same kind of
    device and clock. Ports may differ (a board replugged as another ttyUSB), so only
    ``sim://`` against a real device counts, not the URL."""
    now = {"Responder": responder_name, "Clock": clock_kind,
           "Device": device_kind(spec.device_url)}
    then = {"Responder": stored.responder, "Clock": stored.clock,
            "Device": "simulated" if stored.simulated_device else "real"}
    for key, option in (("Responder", "--responder"), ("Clock", "--clock"),
                        ("Device", "--device")):
        if then[key] != now[key]:
            raise SessionError(
                f"{sidecar}: cannot resume: the session began with {key.lower()} "
                f"{then[key]!r}, now {now[key]!r}; resume with the same {option} or start "
                "another --session")


def check_rows(rows: list[dict[str, str]], plan: TrialPlan, tsv: Path, column: str, *,
               may_skip: bool = False) -> None:
    """The stored rows are the plan's first trials, in order (else the file is another's);
    ``column`` holds the symbol shown (the protocol's set's :attr:`column`).

    ``may_skip``: an adaptive protocol's rows may leave out trials (those a finished staircase
    skipped: :func:`crs_study.session.adaptive.rebuild` checks which); their indices still
    rise."""
    if len(rows) > len(plan.trials):
        raise SessionError(f"{tsv}: {len(rows)} rows but the plan has {len(plan.trials)} trials")
    previous = -1
    for k, row in enumerate(rows):
        index = k
        if may_skip:
            try:
                index = int(row["trial_index"])
            except ValueError:
                index = -1
            if not previous < index < len(plan.trials):
                raise SessionError(f"{tsv}: row {k + 1} holds trial_index "
                                   f"{row['trial_index']!r} after {previous}; the file does not "
                                   "belong to this plan")
            previous = index
        trial = plan.trials[index]
        stored = (row["trial_index"], row["condition"], row[column])
        wanted = (str(trial.index), trial.condition, str(trial.symbol))
        if stored != wanted:
            raise SessionError(f"{tsv}: row {k + 1} holds (trial_index, condition, {column}) = "
                               f"{stored}, the plan says {wanted}; the file does not belong "
                               "to this plan")


def check_frames(frame_log: Path, rows: list[dict[str, str]], plan: TrialPlan, frames,
                 level_column: str | None = None) -> None:
    """The frames stored for the trials so far are those this software renders for them.

    A renderer that draws other setpoints than the one that began the session (the feed cap
    leaving room for the wire's whole-us pulses, say) would otherwise mix two renderings in
    one session silently; the fingerprints cover the bump paths, not the setpoints.
    ``frames``: the session's :class:`~crs_study.session.trials.TrialFrames`. Each row is
    matched to its planned trial by ``trial_index`` (a staircase that stopped skips planned
    trials); a trial whose level the plan leaves open (an adaptive one) is rendered at the
    level its row records in ``level_column``.
    """
    if not rows or not frame_log.exists():
        return
    stored: dict[str, list[str]] = {}
    for line in read_frame_log(frame_log):
        if line["kind"] == "stimulus":
            values = [v for k, v in line.items() if k.startswith("a") and k[1:].isdigit()]
            stored.setdefault(line["trial"], []).append("\t".join(values))
    for row in rows:
        trial = plan.trials[int(row["trial_index"])]
        level = trial.level
        if level is None and level_column is not None and row.get(level_column, "n/a") != "n/a":
            level = float(row[level_column])
        now = frames.setpoint_text(trial.symbol, trial.condition, level)
        if stored.get(str(trial.index), []) != now:
            raise SessionError(
                f"{frame_log}: cannot resume: trial {trial.index} ({trial.condition}, "
                f"{trial.symbol!r}) was shown with other setpoints than this software renders "
                "(the renderer, or the device's dead-band, changed since the session "
                "began); finish it with the software and device options that began it or "
                "start another --session")


def _same_toml(stored: str, current: str) -> bool:
    """Both texts read as the same TOML document (comments and layout aside)."""
    try:
        return tomllib.loads(stored) == tomllib.loads(current)
    except tomllib.TOMLDecodeError:
        return False
