"""crs-study: experiment framework for the continuity reinforcement skeleton haptic display.

The Python API, as a notebook uses it (each name is loaded on first use, so ``import
crs_study`` stays quick and the command line loads only what a command needs)::

    import dataclasses, crs_study
    protocol = crs_study.load_protocol("pilot")             # a file, or a shipped name
    shorter = dataclasses.replace(protocol, design=dataclasses.replace(
        protocol.design, practice_trials=1))                # checked when it is used
    crs_study.validate(shorter).to_frame()                  # trials and wire per condition
    crs_study.dry_run(shorter, participants=4, out="rehearsal")
    analysis = crs_study.analyze("rehearsal", write=False)
    analysis.accuracy.to_frame()                            # the accuracy table

=================  ========================================================================
load_protocol      a protocol file, a shipped protocol's name, or a Protocol changed in
                   Python, read and checked (:mod:`crs_study.protocol`)
make_plan          one participant's trial plan (:class:`TrialPlan`)
validate           a protocol checked and its plan summarised (:class:`ProtocolSummary`)
dry_run            simulated participants on the simulated device (:class:`DryRunResult`)
run_session        one participant's session, begun or resumed (:class:`SessionResult`)
load_dataset       the trials of stored datasets as the analysis sees them
                   (:class:`StudyData`)
analyze            every analysis of the plan (:class:`Analysis`; the report on request)
power              participants needed: the plan's primary test on simulated studies
                   (:class:`PowerResult`)
run_measurement    a measurement protocol's waveforms shown for DIC captures, begun or
                   resumed (:class:`MeasurementRun`)
analyze_measurement  a measurement's DIC captures: D_P and D_S against the model and the
                   paper, the residual map (:class:`MeasuredQuality`)
=================  ========================================================================

The package is one folder per stage of the pipeline, and a stage imports only the stages
listed before it (checked: ``[tool.importlinter]`` in pyproject.toml):

``geometry``   the device file as a Layout (pixels, beams, servos, calibration)
``stimuli``    the bump of Eq. 7, digit strokes, a digit's path over time
``display``    display models: setpoints to the surface the skin meets
``rendering``  a target to setpoints per condition; the one cache of rendered frames
``quality``    the paper's display-quality criteria, mechanics limits, surface measurements
``device``     the LSC-24 wire, the serial device and the simulated one
``dataset``    the stored BIDS dataset: schema, session sidecar, paths, durable writes
``consent``    consent forms, the register, the gate, withdrawal
``adaptive``   staircases and QUEST+: the next level from the responses so far
``protocol``   protocol files, trial plans, the checks against the device
``session``    the runner, the trial loop, resume, dry-runs, responders
``analysis``   the analysis of stored datasets (it reads the dataset alone)
``power_analysis``, ``live``   power by simulation; the display driven live over UDP
``api``        the API functions that join stages (``validate``, ``run_session``)
``commands``, ``cli``, ``benchmarks``   the command line and ``crs-study bench``

Below them, the foundations: ``errors``, ``_files``, ``_toml``, ``_toml_lines``, ``_lazy``,
``clock``, ``signals`` and ``paths`` (the shipped protocols, plans and consent forms).
"""

from importlib.metadata import PackageNotFoundError, version

from crs_study._lazy import lazy_exports
from crs_study.errors import CrsStudyError

try:
    __version__ = version("crs-study")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

#: The public API: name -> the module that owns it.
API = {
    "load_protocol": "crs_study.protocol.loader",
    "make_plan": "crs_study.api",
    "validate": "crs_study.api",
    "dry_run": "crs_study.session.dry_runs",
    "run_session": "crs_study.api",
    "load_dataset": "crs_study.analysis.study_data",
    "analyze": "crs_study.analysis.report",
    "power": "crs_study.power_analysis.api",
    "run_measurement": "crs_study.session.measurement",
    "analyze_measurement": "crs_study.quality.measured_analysis",
    # what they return
    "Protocol": "crs_study.protocol.model",
    "TrialPlan": "crs_study.protocol.plan",
    "ProtocolSummary": "crs_study.api",
    "DryRunResult": "crs_study.session.spec",
    "SessionResult": "crs_study.session.spec",
    "StudyData": "crs_study.analysis.study_data",
    "Analysis": "crs_study.analysis.report",
    "PowerResult": "crs_study.power_analysis.result",
    "MeasurementSpec": "crs_study.session.measurement",
    "MeasurementRun": "crs_study.session.measurement",
    "MeasuredQuality": "crs_study.quality.measured_result",
}

__all__ = ["CrsStudyError", "__version__", *API]

# loaded on first use (see the module docstring); kept once loaded
__getattr__, __dir__ = lazy_exports(__name__, API, globals())
