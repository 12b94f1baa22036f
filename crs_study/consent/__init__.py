"""The consent stage: consent forms, the register, the gate before real sessions, withdrawal.

* :mod:`~crs_study.consent.form`: a versioned consent form, read and checked (:func:`read_form`);
* :mod:`~crs_study.consent.register`: consent and withdrawal events, kept outside every dataset
  (:class:`Register`), and pseudonymous labels;
* :mod:`~crs_study.consent.gate`: no real session without a current consent
  (:func:`require_consent`);
* :mod:`~crs_study.consent.withdrawal_plan`: what a withdrawal removes, exactly the paths and
  rows BIDS names for the participant and the analysis outputs holding them
  (:func:`plan_withdrawal`);
* :mod:`~crs_study.consent.withdrawal`: a participant's data removed from datasets, all or
  nothing (:func:`withdraw`, :func:`recover_withdrawal`).

The stage sits on the dataset (withdrawal removes files from it) and below the protocol (a
protocol names its consent form and is checked against the form's version).
"""

from crs_study.consent.form import ConsentForm, read_form
from crs_study.consent.gate import require_consent
from crs_study.consent.register import (
    REGISTER_ENV,
    REGISTER_FILE,
    ConsentRecord,
    Register,
    check_label,
    default_register_dir,
    generate_label,
)
from crs_study.consent.withdrawal import (
    CRASH_ENV,
    JOURNAL_FILE,
    STAGING_DIR,
    participant_paths,
    pending_withdrawal,
    preview_withdrawal,
    recover_withdrawal,
    running_sessions,
    withdraw,
)
from crs_study.consent.withdrawal_plan import DatasetWithdrawal, plan_withdrawal

__all__ = ["CRASH_ENV", "JOURNAL_FILE", "REGISTER_ENV", "REGISTER_FILE", "STAGING_DIR",
           "ConsentForm", "ConsentRecord", "DatasetWithdrawal", "Register", "check_label",
           "default_register_dir", "generate_label", "participant_paths", "pending_withdrawal",
           "plan_withdrawal", "preview_withdrawal", "read_form", "recover_withdrawal",
           "require_consent", "running_sessions", "withdraw"]
