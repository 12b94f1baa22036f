"""``power()``: how many participants a protocol needs, by simulation.

The library entry point under ``crs-study power``; see :func:`power`.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from crs_study.power_analysis.backends import Backend, Progress, open_backend
from crs_study.power_analysis.design import PowerDesign, PowerError, parse_range
from crs_study.power_analysis.fidelity import run_full
from crs_study.power_analysis.model import GenerativeModel, model_from_pilot
from crs_study.power_analysis.observer import DEFAULT_DRAWS, model_from_observer, predict
from crs_study.power_analysis.protocol_design import design_from_protocol
from crs_study.power_analysis.result import PowerResult, merge
from crs_study.power_analysis.study import PowerTask, run_null_task, run_task

#: Studies per unit of work: fixed (never derived from the number of workers), so the
#: batches, and with them every number, are the same on any backend. The last two units'
#: worth go in units of half the size (:func:`_tasks`).
STUDIES_PER_TASK = 50
DEFAULT_SEED = 20260116
FIDELITIES = ("model", "full")
#: ``participants="auto"``: the range is chosen from the effect (:func:`auto_range`).
AUTO = "auto"
#: Studies per N of the search for the range, and its largest N.
SEARCH_STUDIES = 100
SEARCH_MAX = 256


def power(protocol: Any, *, pilot: str | Path | None = None, effect_scale: float = 1.0,
          participant_sd: float | None = None, participant_slope_sd: float | None = None,
          participants: Any = "auto",
          repetitions: Any = None, studies: int = 1000, seed: int = DEFAULT_SEED,
          target: float = 0.8, fidelity: str = "model", jobs: int = 1, scheduler: Any = None,
          plan: Any = None, model: GenerativeModel | None = None, draws: int | None = None,
          progress: Progress | None = None,
          notify: Callable[[str], None] | None = None) -> PowerResult:
    """Power of the analysis plan's primary test for a protocol, over a range of N.

    Parameters
    ----------
    protocol : a protocol file, a shipped protocol's name or a loaded ``Protocol``.
    pilot : a pilot dataset (mode 1): the primary GLMM fitted to it generates the studies,
        new participants and symbols drawn for each (simr's ``extend``). Default (mode 2):
        the simulated observer's predicted accuracy of every stimulus on the simulated
        device plus a between-participant SD (:mod:`crs_study.power_analysis.observer`).
    effect_scale : multiplies the condition effect(s) of the generating model.
    participant_sd : between-participant SD (logit scale) of mode 2; default: from the
        observer's calibration. With a pilot it replaces the pilot's estimate.
    participant_slope_sd : the SD (logit scale) over participants of the condition effect
        (the random slope the plan's maximal model fits); default: the observer's
        calibration or the pilot's estimate, which it replaces.
    participants, repetitions : ranges (``"4:40:4"``, ``"3:10"``, a number or a list);
        repetitions default to the protocol's. ``participants="auto"`` (the default) chooses
        the range from the effect so that the curve crosses ``target`` (:func:`auto_range`).
    studies : simulated studies per point. seed : the run's seed (the same seed gives the
        same answer on any backend and any number of workers).
    target : the power sought (the one-line answer and the chart's line).
    fidelity : ``"model"`` (modes 1 and 2: trials drawn from the model) or ``"full"`` (mode
        3: every study is real dry-runs of the protocol, analysed as ``analyze`` does: slow,
        for checking the model on a few points).
    jobs : local worker processes. scheduler : a Dask scheduler address or ``Client``.
    plan : the analysis plan (default: the protocol's, as ``analyze`` picks it).
    model : a ready :class:`~crs_study.power_analysis.model.GenerativeModel` (overrides pilot and
        observer). draws : observer noise draws per stimulus (mode 2).
    progress : ``progress(done, total, seconds)`` after each unit of work.
    notify : ``notify(text)`` before a long step that has no progress of its own (the
        observer's predictions).

    Notes
    -----
    Each study is tested exactly as ``analyze`` tests a dataset: the plan's GLMM ``correct ~
    condition + (1 | participant) [+ (1 | symbol)]``, its likelihood-ratio test, alpha from
    the plan, separation and failures handled as there and counted in the result
    (:mod:`crs_study.power_analysis.study`). The power at each point carries its Clopper-Pearson
    95 % interval (Monte Carlo error). Participant k is the same simulated person at every N
    (common random numbers, :mod:`crs_study.power_analysis.simulate`), so the curve rises smoothly.
    """
    started, cpu_started = time.perf_counter(), time.process_time()
    checks = check_options(participants, repetitions, studies, seed, target, fidelity, jobs,
                           effect_scale, participant_sd, participant_slope_sd, draws)
    participants, repetitions_given, studies = checks
    design = design_from_protocol(protocol, plan)   # a protocol or plan error names its file
    reps = repetitions_given or (design.repetitions,)
    notes: list[str] = []
    if fidelity == "full":
        if repetitions_given and reps != (design.repetitions,):
            raise PowerError(f"--repetitions: --fidelity full runs the protocol as written "
                             f"({design.repetitions} repetitions); drop --repetitions or "
                             "edit the protocol")
        if pilot is not None or model is not None:
            raise PowerError("--pilot: --fidelity full runs the simulated observer's "
                             "sessions; a pilot's effect applies to --fidelity model")
        if effect_scale != 1.0:
            raise PowerError("--effect-scale: --fidelity full runs the simulated observer's "
                             "sessions as they are; the scale applies to --fidelity model")
        if participants == AUTO:
            raise PowerError("--participants: --fidelity full runs real dry-runs for each N "
                             "(slow): give the few counts to check, e.g. --participants 4:8:4")
    with open_backend(jobs, scheduler) as backend:      # an unreachable scheduler fails here
        if fidelity == "full":

            generating = _observer_model(design, protocol, participant_sd,
                                         participant_slope_sd, draws, backend, effect_scale,
                                         notify)
            raw = run_full(design, seed, participants, studies, backend, progress)
            notes.append("fidelity full: every study is dry-runs of the protocol by the "
                         "simulated observer, analysed as analyze does; the model shown is "
                         "the observer's prediction, for comparison")
            if any(design.bootstrapped(n) for n in participants):
                null = _tasks(design, generating, seed, participants, reps, studies)
                results = backend.map(run_null_task, null, None, weight=lambda t: t.n_studies)
                raw["null_statistic"] = merge(results)["null_statistic"]
                raw["cpu_seconds"] += backend.cpu_elsewhere(null, [r.seconds for r in results])
                notes.append("fidelity full: below bootstrap_below participants a study's LR "
                             "is referred to as many null studies drawn from the observer's "
                             "prediction without the effect (the bootstrap's reference, once "
                             "a point)")
        else:
            generating = model if model is not None else _generating_model(
                design, protocol, pilot, effect_scale, participant_sd, participant_slope_sd,
                draws, backend, notify)
            if model is not None and effect_scale != 1.0:
                generating = generating.scaled(effect_scale)
            if participants == AUTO:
                participants, note = auto_range(design, generating, seed, reps, target,
                                                backend, notify)
                notes.append(note)
            tasks = _tasks(design, generating, seed, participants, reps, studies)
            results = backend.map(run_task, tasks, progress, weight=lambda t: t.n_studies)
            raw = merge(results)
            raw["cpu_seconds"] = backend.cpu_elsewhere(tasks, [r.seconds for r in results])
        where = backend.describe()
    points = tuple((n, r) for r in (reps if fidelity == "model" else (design.repetitions,))
                   for n in participants)
    # this process's CPU time, and the tasks' own where they ran in other processes
    cpu = raw.pop("cpu_seconds", 0.0) + (time.process_time() - cpu_started)
    if design.method != "laplace":
        notes.append(f"the plan's method is {design.method!r}: every study was fitted by "
                     "fit_glmm itself (the batched fits do the Laplace approximation only)")
    return PowerResult(design, generating, points, raw, seed=seed, target=target,
                       fidelity=fidelity, backend=where,
                       seconds=time.perf_counter() - started, cpu_seconds=cpu,
                       notes=tuple(notes))


def auto_range(design: PowerDesign, model: GenerativeModel, seed: int,
               repetitions: tuple[int, ...], target: float, backend: Backend,
               notify: Callable[[str], None] | None = None) -> tuple[tuple[int, ...], str]:
    """Participant counts whose curve crosses ``target``, chosen from the effect.

    A coarse search: :data:`SEARCH_STUDIES` studies at N = 2, 4, 8, ... (doubling, at most
    :data:`SEARCH_MAX`) until the power at the protocol's first repetition count reaches
    ``target``; the range then runs from a quarter of that N (at least 2) to twice it, in
    about ten steps, so that the curve rises through the target inside it. With power at
    the target already at N = 2, it is 2 to 10 (the answer is then "2 or fewer"); never
    reached, it ends at :data:`SEARCH_MAX`. The search has its own seed (``seed + 1``): the
    curve's studies are not the ones that chose its range. Returns the counts and a note.
    """
    if notify is not None:
        notify("choosing the participant range from the effect (a coarse search) ...")
    n, found, power_at = 2, None, 0.0
    while n <= SEARCH_MAX:
        tasks = _tasks(design, model, seed + 1, (n,), repetitions[:1], SEARCH_STUDIES)
        raw = merge(backend.map(run_task, tasks, None, weight=lambda t: t.n_studies))
        power_at = float(PowerResult(design, model, ((n, repetitions[0]),), raw)
                         .significant().mean())
        if power_at >= target:
            found = n
            break
        n *= 2
    if found is None:
        low, high = max(2, SEARCH_MAX // 8), SEARCH_MAX
    elif found == 2:
        low, high = 2, 10
    else:
        low, high = max(2, found // 4), 2 * found
    step = max(1, round((high - low) / 9))
    counts = tuple(range(low, high + 1, step))
    where = (f"reached {100 * target:g} % near N = {found}" if found is not None else
             f"stayed below {100 * target:g} % up to N = {SEARCH_MAX}")
    return counts, (f"participant range {low}:{counts[-1]}:{step} chosen from the effect: a "
                    f"search of {SEARCH_STUDIES} studies per N {where} (--participants "
                    "sets it)")


def _tasks(design, model, seed, participants, repetitions, studies) -> list[PowerTask]:
    """The studies cut into tasks of ``STUDIES_PER_TASK``, the last two tasks' worth (and
    the remainder) into tasks of half that size: the workers then finish within about half
    a task of each other. (The power point, 1000 studies on 2 jobs, in 20 tasks of 50: one
    core stood idle for 1.7 s at the end, waiting on the other's last task.) A study's
    numbers do not depend on its task (tests/test_power_study.py)."""
    size = STUDIES_PER_TASK
    tail = max(0, studies // size - 2) * size
    starts = [*range(0, tail, size), *range(tail, studies, max(1, size // 2))]
    return [PowerTask(design, model, seed, participants, repetitions, (start, end))
            for start, end in zip(starts, [*starts[1:], studies], strict=True)]


#: Upper bounds of the options (a larger value is a typo, and would run for days or spawn
#: more processes than any machine has): 100,000 studies put the Monte Carlo error of a
#: power near 0.8 at 0.0013; draws beyond 10,000 change no predicted accuracy; 64 local
#: worker processes, as quality's --jobs.
MAX_STUDIES, MAX_DRAWS, MAX_JOBS = 100_000, 10_000, 64


def check_options(participants, repetitions, studies, seed, target, fidelity, jobs,
                  effect_scale, participant_sd, participant_slope_sd=None, draws=None):
    """Every option of :func:`power` checked before anything runs (one line naming the
    option); the participant counts, the repetitions (None: the protocol's) and the studies
    as :func:`power` takes them. The command line calls it before it looks at ``--out``."""
    import math

    for option, value, most in (("--studies", studies, MAX_STUDIES), ("--jobs", jobs, MAX_JOBS),
                                ("--draws", draws, MAX_DRAWS)):
        if isinstance(value, int) and value > most:
            raise PowerError(f"{option}: expected at most {most}, got {value}")

    participants = AUTO if participants == AUTO else parse_range(participants,
                                                                 "--participants", 2)
    repetitions = None if repetitions is None else parse_range(repetitions, "--repetitions",
                                                                1)
    if isinstance(studies, bool) or not isinstance(studies, int) or studies < 2:
        raise PowerError(f"--studies: expected a whole number >= 2, got {studies!r}")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise PowerError(f"--seed: expected a whole number >= 0, got {seed!r}")
    if not isinstance(target, int | float) or not 0 < target < 1:
        raise PowerError(f"--target: expected a power between 0 and 1 (e.g. 0.8), "
                         f"got {target!r}")
    if fidelity not in FIDELITIES:
        raise PowerError(f"--fidelity: expected one of {', '.join(FIDELITIES)}, "
                         f"got {fidelity!r}")
    if isinstance(jobs, bool) or not isinstance(jobs, int) or jobs < 1:
        raise PowerError(f"--jobs: expected a whole number >= 1, got {jobs!r}")
    if not isinstance(effect_scale, int | float) or not math.isfinite(effect_scale) \
            or effect_scale < 0:
        raise PowerError(f"--effect-scale: expected a number >= 0, got {effect_scale!r}")
    for option, value in (("--participant-sd", participant_sd),
                          ("--participant-slope-sd", participant_slope_sd)):
        if value is not None and (not isinstance(value, int | float) or isinstance(value, bool)
                                  or not math.isfinite(value) or value < 0):
            raise PowerError(f"{option}: expected a number >= 0, got {value!r}")
    return participants, repetitions, studies


def _generating_model(design: PowerDesign, protocol, pilot, effect_scale,
                      participant_sd, participant_slope_sd, draws, backend: Backend,
                      notify) -> GenerativeModel:
    if pilot is not None:
        generating = model_from_pilot(design, pilot).with_sds(participant_sd,
                                                              participant_slope_sd)
        return generating.scaled(effect_scale)
    return _observer_model(design, protocol, participant_sd, participant_slope_sd, draws,
                           backend, effect_scale, notify)


def _observer_model(design, protocol, participant_sd, participant_slope_sd, draws, backend,
                    effect_scale, notify):

    source = protocol if hasattr(protocol, "design") else design.protocol_path
    if notify:
        stimuli = len(design.symbols) * len(design.conditions) * len(design.levels)
        notify(f"predicting the simulated observer's accuracy of {stimuli} stimuli "
               f"({draws or DEFAULT_DRAWS} noise draws each)")
    prediction = predict(source, draws or DEFAULT_DRAWS, backend=backend)
    return model_from_observer(design, source, participant_sd, prediction=prediction,
                               participant_slope_sd=participant_slope_sd).scaled(effect_scale)
