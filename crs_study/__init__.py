"""crs-study: experiment framework for the continuity reinforcement skeleton haptic display.

The public surface is small on purpose. Each folder is a stage of the pipeline, and a stage
imports only the stages listed before it (checked: ``[tool.importlinter]`` in pyproject.toml):

``geometry``   the device file as a Layout (pixels, beams, servos, calibration)
``stimuli``    the bump of Eq. 7, digit strokes, a digit's path over time
``display``    display models: setpoints to the surface the skin meets
``rendering``  a target to setpoints per condition; the one cache of rendered frames
``quality``    the paper's display-quality criteria, mechanics limits
``device``     the LSC-24 wire, the serial device and the simulated one
``dataset``    the stored BIDS dataset: schema, session sidecar, paths, durable writes
``consent``    consent forms, the register, the gate, withdrawal
``protocol``   protocol files, trial plans, the checks against the device
``session``    the runner, the trial loop, resume, dry-runs, responders
``analysis``   the analysis of stored datasets (it reads the dataset alone)
``commands``, ``cli``, ``benchmarks``   the command line and ``crs-study bench``

Below them, the foundations: ``errors``, ``_files``, ``_toml``, ``_toml_lines``, ``clock``,
``signals`` and ``paths`` (the shipped protocols, plans and consent forms).
"""

from importlib.metadata import PackageNotFoundError, version

from crs_study.errors import CrsStudyError

try:
    __version__ = version("crs-study")
except PackageNotFoundError:  # running from a source tree that was never installed
    __version__ = "0.0.0+unknown"

__all__ = ["CrsStudyError", "__version__"]
