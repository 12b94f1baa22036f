"""``crs-study analyze`` in a terminal (tmux, 80 x 24): the step under way is shown while it
runs and cleared at the end; the screen then reads the headline first, the warnings after it
grouped by what they concern, and where the files are."""

from __future__ import annotations

import shlex
import sys

from _tmux import Tmux
from analysis_fixtures import FAST_PLAN, dataset, write_plan

#: The suite's fast plan with the chi-square LR (the bootstrap is not what is shown here).
PLAN = FAST_PLAN.replace('random_effects = ["participant"]',
                         'random_effects = ["participant"]\np_value = "chi2"')


def test_progress_while_it_runs_then_the_headline_first_and_warnings_grouped(tmp_path):
    root = dataset(tmp_path / "ds", n_participants=3, repetitions=2)
    plan = write_plan(tmp_path / "plan.toml", PLAN)
    command = " ".join(shlex.quote(a) for a in (
        sys.executable, "-m", "crs_study", "analyze", str(root), "--plan", str(plan),
        "--out", str(tmp_path / "out"), "--jobs", "1"))
    with Tmux(command, tmp_path, env={"MPLBACKEND": "Agg"}) as term:
        shown = term.wait_for("analyze: ", timeout=120)      # a step, shown as it runs
        assert any(line.startswith("analyze: ") and line.rstrip().endswith(" s")
                   for line in shown.splitlines())
        assert term.exit_code(timeout=600) == 0
        # the whole terminal, scrolled-off lines included (capture-pane -S -)
        history = term._tmux("capture-pane", "-p", "-J", "-S", "-", "-t", term.name)
        screen = [line for line in history.splitlines() if line.strip()]
    assert not any(line.startswith("analyze: ") for line in screen)   # cleared at the end
    assert screen[0].startswith("crs ") and "GLMM odds ratio" in "".join(screen[:4]), screen
    warnings = [i for i, line in enumerate(screen) if line.startswith("crs-study analyze: w")]
    report = next(i for i, line in enumerate(screen) if line.startswith("report: "))
    assert warnings and max(warnings) < report
    groups = [screen[i].split("[", 1)[1].split("]")[0] for i in warnings]
    runs = [g for k, g in enumerate(groups) if k == 0 or g != groups[k - 1]]
    assert len(runs) == len(set(runs))                      # each group's lines together
