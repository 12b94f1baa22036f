"""The headline: one line with each condition's accuracy and the primary comparison(s).

It is written from ``results.json``'s content alone (the flags of a comparison are fields,
never read back out of its ``method`` label), so a reader can rebuild it from the file.
"""

from __future__ import annotations

import math

from crs_study.analysis.accuracy import PARTICIPANT_LEVEL, POOLED_CI_METHOD


def format_p(p: float | None) -> str:
    """``p = 0.0123``, ``p = 3.4e-07`` or ``p < 1e-16`` (never ``p = 0``)."""
    if p is None or not math.isfinite(p):
        return "p n/a"
    if p < 1e-16:
        return "p < 1e-16"
    return f"p = {p:.3g}" if p >= 1e-4 else f"p = {p:.2e}"


def headline(results: dict) -> str:
    """One line: the answer to the study's question (:func:`accuracy_headline`, or for an
    adaptive study :func:`threshold_headline`)."""
    thresholds = results.get("thresholds")
    if thresholds and not thresholds.get("skipped", True) and thresholds.get("comparisons"):
        return threshold_headline(results)
    return accuracy_headline(results)


def threshold_headline(results: dict) -> str:
    """An adaptive study's line: each condition's threshold against the reference's (the
    procedure's own estimates, paired by participant: ratio on a log scale, else the
    difference), the paired test; then the accuracies, which the procedure steers towards
    its target rate and so answer nothing on their own."""
    thresholds = results["thresholds"]
    parts = []
    comparisons = thresholds["comparisons"]
    by_condition = {}
    for c in comparisons:          # the procedure's estimate first, the fit where it is alone
        by_condition.setdefault(c["condition"], c) if c["method"] == "procedure" else None
    for c in comparisons:
        by_condition.setdefault(c["condition"], c)
    column = thresholds["level_column"]
    rate = f"{100 * thresholds['target_rate']:.3g} % correct"
    for condition, c in by_condition.items():
        if c["ratio"] is not None:
            low, high = c["ratio_ci95"]
            size = f"{c['ratio']:.3g} x {c['reference']} [{low:.3g}, {high:.3g}]"
        else:
            low, high = c["ci95"]
            size = f"{c['mean_difference']:+.3g} vs {c['reference']} [{low:+.3g}, {high:+.3g}]"
        parts.append(f"{condition} threshold {size} (paired t({c['df']}) = {c['t']:.3g}, "
                     f"{format_p(c['pvalue'])}, {c['n_pairs']} participants)")
    text = (f"{'; '.join(parts)}; thresholds: {column} at {rate} ({thresholds['procedure']} "
            f"estimates, 95 % intervals)")
    accuracy = ", ".join(f"{condition} {100 * row['accuracy']:.1f} %"
                         for condition, row in results["conditions"].items())
    return f"{text}; accuracy steered by the procedure: {accuracy}"


def accuracy_headline(results: dict) -> str:
    """One line: each condition's accuracy with an interval that accounts for participants
    (``conditions.<c>.headline``: the mean of participant accuracies with the t interval
    across participants, or the pooled Wilson interval where that has no width, labelled),
    then the primary comparison(s). A separated condition's odds ratio is given as its
    one-sided profile limit ("> 367 ... upper limit infinite"), never as the penalised
    estimate; a logistic regression without participant variance says so."""
    parts, methods = [], []
    reference = results["reference"]
    order = [c for c in results["conditions"] if c != reference] + [reference]
    level = f"{100 * (1 - results['alpha']):g} %"
    for condition in order:
        row = results["conditions"].get(condition)
        if row:
            shown = row.get("headline") or {"accuracy": row["accuracy"], "ci95": row["ci95"],
                                            "method": POOLED_CI_METHOD}
            low, high = shown["ci95"]
            parts.append(f"{condition} {100 * shown['accuracy']:.1f} % "
                         f"[{100 * low:.1f}, {100 * high:.1f}]")
            methods.append(shown["method"])
    text = " vs ".join(parts)
    if parts:
        if set(methods) == {PARTICIPANT_LEVEL}:
            text += (f" (mean of {results['n_participants']} participants, {level} t interval "
                     "across participants)")
        elif len(set(methods)) == 1:
            text += f" ({level} {methods[0]})"
        else:
            text += f" ({level} intervals: {'; '.join(dict.fromkeys(methods))})"
    glmm = [c for c in results["comparisons"] if c["primary"]]
    for c in glmm:
        name = "GLMM odds ratio" if c["test"] == "glmm" else "odds ratio (Fisher)"
        notes = []
        if c["logistic_regression"]:
            notes.append("logistic regression: no participant variance estimable")
        if len(glmm) > 1:
            notes.insert(0, f"{c['condition']} vs {c['reference']}")
        who = f" ({'; '.join(notes)})" if notes else ""
        if c.get("separated"):
            text += f"; {name}{who} {_separated_text(c, level)}, {format_p(c['p_value'])}"
            continue
        low, high = ("0" if v is None and k == 0 else "inf" if v is None else f"{v:.2f}"
                     for k, v in enumerate(c["ci95"]))
        how = (f" ({_bootstrap_text(c['bootstrap'])})"
               if c.get("p_method") == "bootstrap" else "")
        text += (f"; {name}{who} {c['estimate']:.2f} [{low}, {high}], "
                 f"{format_p(c['p_value'])}{how}")
    if not glmm:
        text += "; no comparison of conditions (see warnings)"
    return text


def _bootstrap_text(bootstrap: dict) -> str:
    """How a bootstrap p was reached: all B replicates, or Besag and Clifford's early stop."""
    if bootstrap.get("stopped_early"):
        return (f"parametric bootstrap, {bootstrap['exceed']} of {bootstrap['used']} "
                f"replicates reached the observed LR")
    return f"parametric bootstrap, B = {bootstrap['used']}"


def _separated_text(c: dict, level: str) -> str:
    """``> 367 (ML estimate infinite: ...; upper limit infinite)`` for a separated odds ratio."""
    low, high = c["ci95"]
    why = f"ML estimate infinite: a condition at 0 or 100 %; one-sided {level} profile limit"
    if low is not None:
        return f"> {low:.3g} ({why}, upper limit infinite)"
    if high is not None:
        return f"< {high:.3g} ({why}, lower limit 0)"
    return "not estimable (ML estimate infinite, no finite profile limit)"
