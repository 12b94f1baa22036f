"""The gate before and during a session: a current consent on the protocol's form, or a refusal.

Who passes through it (:func:`needs_consent`): every session under a person's label, on every
device (``sim://`` included) and with every responder. Only a simulated participant skips it:
a label in the simulated label space (``sim...``, which the register refuses for a person,
:func:`crs_study.dataset.is_simulated_label`) answered by a simulated responder on the
simulated device; such a label with a person at the keypad or on a real device is refused.
So a withdrawn person's label cannot be run as a "simulation", and a person can never be
recorded without a consent record.

The gate passes a participant whose latest consent event in the register
(:mod:`crs_study.consent.register`) is on the protocol's consent-form version and on that very
text; a withdrawn participant is refused. Nothing is written before the gate has passed, and
a running session asks again before every trial (:class:`ConsentGate`: a ``stat`` of the
register, read again only when it changed), so a withdrawal stops it at the next trial
boundary.
"""

from __future__ import annotations

from pathlib import Path

from crs_study.consent.form import ConsentForm
from crs_study.consent.register import ConsentRecord, Register
from crs_study.dataset import is_simulated_label
from crs_study.errors import ConsentError


def needs_consent(participant: str, device_url: str, simulated_responder: bool) -> bool:
    """Whether a session must pass the gate (module docstring); a simulated label in a session
    that is not wholly simulated is a one-line :class:`ConsentError`."""
    if not is_simulated_label(participant):
        return True
    if simulated_responder and device_url.startswith("sim://"):
        return False
    who = "a simulated responder" if simulated_responder else "a person"
    raise ConsentError(
        f"participant label {participant!r} is a simulated participant's (it begins with "
        f"'sim'), but this session has {who} on {device_url}: simulated labels are for "
        "simulated responders on sim:// only; a person needs their own label and a consent "
        "record (crs-study consent record)")


def require_consent(register_dir: str | Path | None, participant: str, form_version: str,
                    form: ConsentForm | None = None) -> ConsentRecord:
    """The gate: a current consent on ``form_version`` or a refusal.

    With ``form`` (the protocol's consent form) the consent must also be on that very text
    (same sha256): a form edited without a new version is refused, not silently accepted.
    """
    register = Register(register_dir)
    record = register.records().get(participant)
    withdrawn = register.withdrawn().get(participant)
    if withdrawn is not None:
        raise ConsentError(
            f"participant {participant!r} withdrew consent on {withdrawn}; no session may run"
        )
    if record is None:
        raise ConsentError(
            f"no consent record for participant {participant!r} in {register.directory}; "
            f"record it first: crs-study consent record --participant {participant} "
            f"--form FORM --experimenter INITIALS"
        )
    if record.form_version != form_version:
        raise ConsentError(
            f"participant {participant!r} consented to form version {record.form_version!r}, "
            f"the protocol needs version {form_version!r}; record consent on the current form"
        )
    if form is not None and record.form_sha256 != form.sha256:
        raise ConsentError(
            f"participant {participant!r} consented on a form whose text differs from "
            f"{form.path} (sha256 {record.form_sha256[:12]} vs {form.sha256[:12]}, both "
            f"version {form_version!r}); give a changed form a new version and record "
            "consent on it")
    return record


class ConsentGate:
    """The gate of one session: :meth:`check` before anything is written, :meth:`recheck`
    before every trial (a ``stat`` of the register; the full check again when it changed,
    and when it cannot be read: a register that vanished closes the gate)."""

    def __init__(self, register_dir: str | Path | None, participant: str, form_version: str,
                 form: ConsentForm | None = None) -> None:
        self.register = Register(register_dir)
        self.participant = participant
        self.form_version = form_version
        self.form = form
        self._stamp: tuple[int, int, int] | None = None

    def check(self) -> ConsentRecord:
        stamp = self.register.stamp()
        record = require_consent(self.register.directory, self.participant, self.form_version,
                                 self.form)
        self._stamp = stamp
        return record

    def recheck(self) -> None:
        """Raise :class:`ConsentError` when the consent no longer holds."""
        if self._stamp is None or self.register.stamp() != self._stamp:
            self.check()
