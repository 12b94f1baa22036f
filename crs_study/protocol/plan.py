"""Trial plans: a protocol, a participant and a session expanded into a fixed list of trials.

Determinism (the cross-machine contract)
    The seed is ``int.from_bytes(sha256("crs-study plan v1" NUL study_id NUL version NUL
    participant NUL session)[:8], "big")``; the generator is
    ``numpy.random.Generator(PCG64(seed))``. Only ``Generator.random()`` (uniform doubles in
    [0, 1), a stable function of PCG64's output) is drawn; every choice is made from those
    doubles here (index = floor(u n)), not by numpy's shuffling or sampling routines, whose
    algorithms may change between numpy versions. So the same inputs give the same plan on
    any machine and numpy version; ``tests/test_plan.py`` pins one plan.

Design
    Blocks: with ``ordering = "blocked"`` each block shows one condition. The block order
    comes from the counterbalance index k (the participant's order of arrival, from 0), not
    from the seed: ``none`` A B ..; ``alternate`` A B for even k, B A for odd k; ``abba``
    A B B A for even k, B A A B for odd k (repetitions r of a condition dealt to its two
    blocks as r = 0, 2, 4 .. and 1, 3, ..); ``latin`` row k mod rows of a balanced Latin
    square (Williams 1949; 2n rows for odd n). ``ordering = "interleaved"``: one block with
    every condition mixed.

    Practice: ``practice_trials`` per condition at the start of the condition's first block
    (or of every block), symbols cycling through a shuffled list of the protocol's symbols
    (one cycle per block, dealt to its conditions in turn), with feedback when the protocol
    says so. Test trials: every symbol ``repetitions`` times
    per condition. Within a block the order is random under the run constraint: no symbol
    more than ``max_same_symbol_run`` (a digit protocol: ``max_same_digit_run``) times in a
    row, practice and test trials together.

    The constraint is met constructively: each next trial is drawn with probability
    proportional to the remaining count of its (condition, symbol) among those that would not
    extend a run beyond the limit; a dead end (only the blocked symbol left) restarts the
    block with the same generator (rare: a fraction of a percent of blocks for 10 symbols).

    Levels: a protocol with ``[levels]`` crosses them with conditions and symbols: every
    (condition, symbol, level) cell gets ``repetitions`` test trials, ordered as above (the
    run constraint is on symbols, whatever their level). Practice trials also cycle through
    a shuffled list of the levels (drawn after the symbols' cycle). Without ``[levels]``
    nothing is drawn for them, so such a protocol's plans are those of earlier versions.

    Symbols: only their order in the protocol matters to the draws (ints for the digit set,
    strings for the others), and a trial's row of the fingerprint writes ``str(symbol)``, so
    the plans and fingerprints of digit protocols are those of versions before stimulus
    sets.

    Adaptive: a protocol with ``[adaptive]`` has one block per condition (``repetitions =
    1``) of ``adaptive.trials`` test trials whose level the block's procedure chooses when the
    trial comes (``level`` is None in the plan); the symbols are dealt evenly (each
    ``trials // n`` times, and once more for ``trials mod n`` of them, drawn as the first
    symbols of a shuffled list). Practice trials show ``adaptive.practice_level``.

    Breaks: ``break_before`` on a trial preceded by a multiple of ``break_every`` trials of
    its block. Block starts carry the condition's prompt to the experimenter instead.
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

from crs_study.errors import ProtocolError
from crs_study.geometry.layout import Layout
from crs_study.protocol.model import Protocol
from crs_study.stimuli.sets import DEFAULT_SET, set_column
from crs_study.stimuli.stimulus import make_stimulus
from crs_study.stimuli.strokes import Symbol
from crs_study.stimuli.symbol_set import spell

#: Restarts allowed per block before the run constraint is declared unsatisfiable.
MAX_RESTARTS = 10_000
#: How the default set names the run limit and its symbols (``max_same_digit_run``).
_DEFAULT_RUN_KEY = spell("max_same_symbol_run", set_column(DEFAULT_SET))
_DEFAULT_PLURAL = f"{set_column(DEFAULT_SET)}s"


@dataclass(frozen=True)
class PlannedTrial:
    """One trial of a plan (see the contract in the module docstring)."""

    index: int
    trial_type: Literal["practice", "test"]
    block: int
    condition: str
    repetition: int
    symbol: Symbol
    feedback: bool
    break_before: bool
    prompt_before: str | None
    level: float | None = None  # the varied stimulus parameter's value ([levels]), else None


@dataclass(frozen=True)
class TrialPlan:
    """The trials of one session, in order, and the seed and counterbalance that made them."""

    seed: int
    counterbalance: int
    trials: tuple[PlannedTrial, ...]
    block_conditions: tuple[str, ...] = ()

    def __len__(self) -> int:
        return len(self.trials)

    def count(self, trial_type: str | None = None, condition: str | None = None,
              level: float | None = None) -> int:
        return sum(1 for t in self.trials
                   if (trial_type is None or t.trial_type == trial_type)
                   and (condition is None or t.condition == condition)
                   and (level is None or t.level == level))

    def sha256(self) -> str:
        """Fingerprint of the plan (seed, counterbalance, every trial), e.g. to check a resume.

        A trial's level is appended to its row only when it has one (``repr`` of the float),
        so plans without levels keep their earlier fingerprints."""
        rows = [f"{self.seed}\t{self.counterbalance}"]
        rows += ["\t".join(str(v) for v in (t.index, t.trial_type, t.block, t.condition,
                                              t.repetition, t.symbol, int(t.feedback),
                                              int(t.break_before), t.prompt_before or "")
                           + (() if t.level is None else (repr(float(t.level)),)))
                 for t in self.trials]
        return hashlib.sha256("\n".join(rows).encode()).hexdigest()


def plan_seed(study_id: str, version: str, participant: str, session: int) -> int:
    """The plan's seed: the first 8 bytes (big-endian) of a sha256 of the identifying fields."""
    text = "\0".join(["crs-study plan v1", study_id, version, participant, str(int(session))])
    return int.from_bytes(hashlib.sha256(text.encode("utf-8")).digest()[:8], "big")


def williams_square(n: int) -> list[list[int]]:
    """Balanced Latin square rows for n treatments (Williams 1949); 2n rows when n is odd.

    First row 0, 1, n-1, 2, n-2, ...; row i adds i mod n. Each treatment follows each other
    equally often (once for even n, twice over the 2n rows for odd n).
    """
    first = [0]
    low, high = 1, n - 1
    while len(first) < n:
        first.append(low)
        low += 1
        if len(first) < n:
            first.append(high)
            high -= 1
    rows = [[(c + i) % n for c in first] for i in range(n)]
    if n % 2:
        rows += [row[::-1] for row in rows]
    return rows


def block_order(protocol: Protocol, counterbalance: int) -> tuple[str, ...]:
    """Conditions of the blocks, in order, for counterbalance index ``counterbalance``."""
    if counterbalance < 0:
        raise ProtocolError(f"counterbalance index must be >= 0, got {counterbalance!r}")
    base = list(protocol.conditions)
    scheme = protocol.design.counterbalancing
    if protocol.design.ordering == "interleaved":
        return ("+".join(base),)
    if scheme == "none":
        return tuple(base)
    if scheme == "alternate":
        return tuple(base if counterbalance % 2 == 0 else base[::-1])
    if scheme == "abba":
        first = base if counterbalance % 2 == 0 else base[::-1]
        return tuple(first + first[::-1])
    rows = williams_square(len(base))
    return tuple(base[i] for i in rows[counterbalance % len(rows)])


def counterbalance_cycle(protocol: Protocol) -> int:
    """P: counterbalance indices k and k + P always get the same block order.

    1 for ``none`` and interleaved designs, 2 for ``alternate`` and ``abba``, the number of
    rows of the Williams square for ``latin`` (n conditions, 2n when n is odd).
    """
    scheme = protocol.design.counterbalancing
    if protocol.design.ordering == "interleaved" or scheme == "none":
        return 1
    if scheme in ("alternate", "abba"):
        return 2
    return len(williams_square(len(protocol.conditions)))


def block_orders(protocol: Protocol) -> tuple[tuple[str, ...], ...]:
    """The block order of counterbalance index k = 0 .. P - 1 (:func:`counterbalance_cycle`);
    index k gets ``block_orders(protocol)[k % P]``."""
    return tuple(block_order(protocol, k) for k in range(counterbalance_cycle(protocol)))


def trial_seconds(protocol: Protocol, plan: TrialPlan, layout: Layout | None = None
                  ) -> list[float]:
    """Expected duration of each trial of ``plan`` (s): its stimulus, the expected response
    time from offset (``responses.expected_response_s``), the inter-trial interval, and the
    break before it when it has one (``design.break_duration_s``). The experimenter's block
    changes (mounting the skeleton) are not counted. An adaptive trial, whose level is chosen
    as it comes, is counted at the middle level of the procedure's grid."""
    layout = layout if layout is not None else protocol.layout()
    durations: dict[tuple[Symbol, float | None], float] = {}
    seconds = []
    middle = None
    if protocol.adaptive is not None:
        grid = protocol.adaptive.grid()
        middle = grid[len(grid) // 2]
    for trial in plan.trials:
        key = (trial.symbol, trial.level if trial.level is not None else middle)
        if key not in durations:
            durations[key] = make_stimulus(protocol, layout, *key).duration_s
        seconds.append(durations[key] + protocol.responses.expected_response_s
                       + protocol.inter_trial_interval_s
                       + (protocol.design.break_duration_s if trial.break_before else 0.0))
    return seconds


def expected_duration_s(protocol: Protocol, plan: TrialPlan, layout: Layout | None = None
                        ) -> float:
    """The session's expected duration (s): the sum of :func:`trial_seconds`."""
    return float(sum(trial_seconds(protocol, plan, layout)))


class _Draw:
    """Choices from ``Generator.random()`` doubles only (see the module docstring)."""

    def __init__(self, seed: int) -> None:
        self.rng = np.random.Generator(np.random.PCG64(seed))

    def index(self, n: int) -> int:
        return min(int(self.rng.random() * n), n - 1)

    def weighted(self, weights: Sequence[int]) -> int:
        total = sum(weights)
        target = self.rng.random() * total
        running = 0
        for i, w in enumerate(weights):
            running += w
            if target < running:
                return i
        return max(i for i, w in enumerate(weights) if w > 0)

    def shuffled(self, items: Sequence) -> list:
        out = list(items)
        for i in range(len(out) - 1, 0, -1):  # Fisher-Yates
            j = self.index(i + 1)
            out[i], out[j] = out[j], out[i]
        return out


def constrained_order(groups: dict[tuple, list[int]], max_run: int, draw: _Draw,
                      history: Sequence[Symbol] = (), run_key: str = _DEFAULT_RUN_KEY,
                      plural: str = _DEFAULT_PLURAL) -> list[tuple]:
    """Order items so no symbol runs longer than ``max_run``.

    ``groups`` maps a cell (condition, symbol) or (condition, symbol, level) to its
    repetitions (taken smallest first); the items returned are the cell's fields then the
    repetition. ``history`` is the symbols shown just before (so the constraint holds across
    the junction). ``run_key`` and ``plural`` name the limit and the symbols in the error
    (by default as the default set names them).
    """
    keys = list(groups)
    for _ in range(MAX_RESTARTS):
        remaining = {k: sorted(v) for k, v in groups.items()}
        recent = list(history)
        out: list[tuple] = []
        total = sum(len(v) for v in remaining.values())
        while len(out) < total:
            blocked = recent[-1] if len(recent) >= max_run and \
                len(set(recent[-max_run:])) == 1 else None
            weights = [len(remaining[k]) if k[1] != blocked else 0 for k in keys]
            if not any(weights):
                break  # dead end: restart
            key = keys[draw.weighted(weights)]
            out.append((*key, remaining[key].pop(0)))
            recent.append(key[1])
        else:
            return out
    noun = plural.removesuffix("s")
    raise ProtocolError(f"design.{run_key}: cannot order {sum(map(len, groups.values()))}"
                        f" trials with no {noun} more than {max_run} times in a row")


def make_plan(protocol: Protocol, participant: str, session: int, counterbalance: int
              ) -> TrialPlan:
    """The session's trial plan (deterministic; see the module docstring)."""
    seed = plan_seed(protocol.study_id, protocol.version, participant, session)
    draw = _Draw(seed)
    design = protocol.design
    symbols = protocol.symbols
    run = {"run_key": protocol.symbol_set.spelled("max_same_symbol_run"),
           "plural": protocol.symbol_set.plural}
    adaptive = protocol.adaptive
    levels = protocol.levels.values if protocol.levels is not None and adaptive is None \
        else None
    blocks = block_order(protocol, counterbalance)
    conditions_of = [b.split("+") for b in blocks]
    appearances: dict[str, int] = {}
    trials: list[PlannedTrial] = []

    for block, conditions in enumerate(conditions_of):
        practice_groups: dict[tuple, list[int]] = {}
        test_groups: dict[tuple, list[int]] = {}
        practising: list[str] = []
        for condition in conditions:
            nth = appearances.get(condition, 0)
            appearances[condition] = nth + 1
            per_condition = blocks.count(condition) if design.ordering == "blocked" else 1
            reps = [r for r in range(design.repetitions) if r % per_condition == nth]
            if adaptive is not None:  # the block's track: trials dealt evenly to the symbols
                per_symbol, extra = divmod(adaptive.trials, len(symbols))
                more = set(draw.shuffled(symbols)[:extra])
                for symbol in symbols:
                    test_groups[(condition, symbol)] = list(range(per_symbol + (symbol in more)))
            for symbol in symbols if adaptive is None else ():
                if levels is None:
                    test_groups[(condition, symbol)] = list(reps)
                else:
                    for level in levels:
                        test_groups[(condition, symbol, level)] = list(reps)
            if design.practice_trials and (nth == 0 or design.practice_in == "every-block"):
                practising.append(condition)
        # One cycle of shuffled symbols for the block's practice, dealt to its conditions in
        # turn: symbol counts differ by at most one, so the run constraint can always be met.
        n_practice = design.practice_trials * len(practising)
        cycle: list[Symbol] = []
        while len(cycle) < n_practice:
            cycle += draw.shuffled(symbols)
        level_cycle: list[float] = []
        while levels is not None and len(level_cycle) < n_practice:
            level_cycle += draw.shuffled(levels)
        for i, symbol in enumerate(cycle[:n_practice]):
            cell = (practising[i % len(practising)], symbol) if levels is None else \
                (practising[i % len(practising)], symbol, level_cycle[i])
            shown = practice_groups.setdefault(cell, [])
            shown.append(len(shown))  # repetition: the cell's nth practice trial
        practice = constrained_order(practice_groups, design.max_same_symbol_run, draw, **run)
        test = constrained_order(test_groups, design.max_same_symbol_run, draw,
                                 history=[p[1] for p in practice], **run)
        prompt = None
        if design.ordering == "blocked":
            prompt = protocol.prompt(conditions[0]) or \
                f"Block {block + 1} of {len(blocks)}: {conditions[0]}"
        items = [("practice", *p) for p in practice] + [("test", *t) for t in test]
        for position, (kind, condition, symbol, *rest) in enumerate(items):
            level, repetition = (None, rest[0]) if levels is None else rest
            if adaptive is not None and kind == "practice":
                level = adaptive.practice
            feedback = protocol.feedback_practice if kind == "practice" else \
                protocol.feedback_test
            trials.append(PlannedTrial(
                index=len(trials), trial_type=kind, block=block, condition=condition,
                repetition=repetition, symbol=symbol, feedback=feedback,
                break_before=bool(design.break_every and position
                                  and position % design.break_every == 0),
                prompt_before=prompt if position == 0 else None, level=level,
            ))
    return TrialPlan(seed, counterbalance, tuple(trials), blocks)
