"""What a session says to the people in the room.

The experimenter sees a prompt at each block start (the protocol's ``[conditions.prompts]``,
or the plan's "Block k of n"), at each break (:data:`BREAK_PROMPT`) and before a resumed
session's first trial (:func:`resume_prompt`). The task's description and the participant's
instructions, stored in each session's sidecar (``TaskDescription``, ``Instructions``), are
the stimulus set's (:class:`~crs_study.stimuli.symbol_set.StimulusSet`).
"""

from __future__ import annotations

from crs_study.protocol.plan import TrialPlan

#: The prompt of a break without a block start.
BREAK_PROMPT = "Break: rest, then continue"


def resume_prompt(plan: TrialPlan, first: int) -> str:
    """What the experimenter sees before a resumed session's first trial: where it stands and
    the current block's prompt (mount or remove the skeleton), which was shown before the
    interruption and may no longer hold."""
    trial = plan.trials[first]
    text = f"Resuming at trial {first + 1} of {len(plan.trials)}"
    if trial.prompt_before:  # the block starts here: its own prompt follows
        return text
    block_start = next((t for t in reversed(plan.trials[:first])
                        if t.block == trial.block and t.prompt_before), None)
    return f"{text}. {block_start.prompt_before}" if block_start else text
