"""The plan's exclusion rules applied to the trials (:func:`apply_exclusions`)."""

from __future__ import annotations

import pandas as pd

from crs_study.analysis.plan import Exclusions


def apply_exclusions(trials: pd.DataFrame, rules: Exclusions
                     ) -> tuple[pd.DataFrame, dict[str, dict[str, int]]]:
    """Mark excluded trials (first reason wins) and count them per reason and condition.

    Returns the table with ``excluded`` and ``exclusion`` set, and ``{reason: {condition: n}}``
    for every reason the plan enables (zeros included, so a report shows each rule applied).
    """
    trials = trials.copy()
    rt = trials[rules.rt_column]
    test_rt = trials["response_time"]
    rules_in_order = [
        ("practice", rules.practice, trials["trial_type"] == "practice"),
        ("device_fault", rules.device_faults, trials["device_fault"]),
        ("timeout", rules.timeouts == "exclude", trials["timed_out"] | trials["correct"].isna()),
        ("anticipation", rules.anticipation_s > 0, test_rt < rules.anticipation_s),
        ("slow", rules.max_response_time_s > 0, rt > rules.max_response_time_s),
    ]
    if rules.timeouts == "count_as_error":
        timed_out = trials["timed_out"] | trials["correct"].isna()
        trials.loc[timed_out, "correct"] = 0.0
    reason = pd.Series("", index=trials.index, dtype=object)
    counts: dict[str, dict[str, int]] = {}
    conditions = sorted(trials["condition"].unique())
    for name, enabled, mask in rules_in_order:
        if not enabled:
            continue
        new = mask.fillna(False).astype(bool) & (reason == "")
        reason[new] = name
        per_condition = trials.loc[new, "condition"].value_counts()
        counts[name] = {c: int(per_condition.get(c, 0)) for c in conditions}
    trials["exclusion"] = reason.astype(str)
    trials["excluded"] = reason != ""
    return trials, counts
