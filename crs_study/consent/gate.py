"""The gate before a real session: a current consent on the protocol's form, or a refusal.

A session on any device but ``sim://`` starts only for a participant whose latest consent
event in the register (:mod:`crs_study.consent.register`) is on the protocol's consent-form
version and on that very text; a withdrawn participant is refused. Nothing is written before
the gate has passed.
"""

from __future__ import annotations

from pathlib import Path

from crs_study.consent.form import ConsentForm
from crs_study.consent.register import ConsentRecord, Register
from crs_study.errors import ConsentError


def require_consent(register_dir: str | Path | None, participant: str, form_version: str,
                    form: ConsentForm | None = None) -> ConsentRecord:
    """The gate before a real session: a current consent on ``form_version`` or a refusal.

    With ``form`` (the protocol's consent form) the consent must also be on that very text
    (same sha256): a form edited without a new version is refused, not silently accepted.
    """
    register = Register(register_dir)
    record = register.records().get(participant)
    if record is None:
        raise ConsentError(
            f"no consent record for participant {participant!r} in {register.directory}; "
            f"record it first: crs-study consent record --participant {participant} "
            f"--form FORM --experimenter INITIALS"
        )
    if record.withdrawn_at:
        raise ConsentError(
            f"participant {participant!r} withdrew consent on {record.withdrawn_at}; "
            "no session may run"
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


