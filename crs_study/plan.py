"""Trial plans, at their former path: :mod:`crs_study.protocol.plan` holds them now.

The plan is part of the protocol stage (the protocol's warnings are computed from an example
plan), so it lives in the :mod:`crs_study.protocol` package; this module re-exports its
public names for code written against ``crs_study.plan``.
"""

from crs_study.protocol.plan import (  # noqa: F401  (re-exported)
    MAX_RESTARTS,
    PlannedTrial,
    TrialPlan,
    block_order,
    block_orders,
    constrained_order,
    counterbalance_cycle,
    expected_duration_s,
    make_plan,
    plan_seed,
    trial_seconds,
    williams_square,
)
