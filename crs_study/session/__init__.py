"""The session stage: a protocol's trials played on a device, answered, and stored durably.

* :mod:`~crs_study.session.spec`: what a session is asked to do and how it ended;
* :mod:`~crs_study.session.runner`: one session, begun or resumed (:func:`run_session`);
* :mod:`~crs_study.session.resume`: what a resumed session must match;
* :mod:`~crs_study.session.trials`: the trial loop (stimulus, response, the stored row);
* :mod:`~crs_study.session.state`: the mutable state of a run and its sidecar writes;
* :mod:`~crs_study.session.prompts`: what the experimenter and the participant are told;
* :mod:`~crs_study.session.dry_runs`: many simulated participants (:func:`dry_run`);
* :mod:`~crs_study.session.measurement`: a measurement of the display's surface (DIC
  captures of target waveforms, :func:`~crs_study.session.measurement.run_measurement`);
* :mod:`~crs_study.session.responders`: who answers (keypad, script, simulated observers).
"""

from crs_study.session.dry_runs import dry_run, simulated_labels
from crs_study.session.runner import run_session, seed_check
from crs_study.session.spec import DryRunResult, SessionResult, SessionSpec

__all__ = ["DryRunResult", "SessionResult", "SessionSpec", "dry_run", "run_session", "seed_check",
           "simulated_labels"]
