"""Display conditions: what a condition means, in one object that every stage asks.

A condition is how a target is put on the display, and what follows from that for the rest of
the pipeline. :class:`Condition` holds it:

``render``
    the strategy: ``(layout, target, geometry) -> raw setpoints`` in actuator order (pixel
    heights, then each beam's start and end feed); :class:`~crs_study.rendering.Renderer`
    applies the clamp policy and the feed cap to what it returns.
``drives_beams``
    True when the skeleton is mounted and its boundary servos feed the beams: the protocol's
    device checks then include the bump's curvature against the beam's yield curvature and
    the no-collapse number (Eq. 4), a measurement block asks the experimenter to mount the
    skeleton, and a simulated participant's benefit draw counts on the skeleton's side.
``display_model``
    the display model (:data:`crs_study.display.MODELS`) whose surface the skin meets: what a
    simulated participant feels and what a surface measurement is compared with.
``fast_path``
    True when, for a :class:`~crs_study.stimuli.targets.Bump`, the render strategy equals
    :class:`~crs_study.rendering.bump_path.BumpPath` (pixel heights sampled from the bump,
    and with ``drives_beams`` each beam fed its arc excess split evenly), so the renderer may
    take that path (the same setpoints within 1e-10 mm).

The two shipped conditions are those of Zhang et al., "Continuity reinforcement skeleton for
pixel-based haptic display", Nature Communications (2024): ``pixel-only`` (the pixels alone,
under the stretched fabric sewn to their tips: the piecewise-linear surface between them) and
``crs`` (the compressed beams guided by the pixels, Supplementary Discussion 7 for the feed).
A study adds its own with :func:`register_condition` (for example an optimised feed rule, or
the paper's other display models on the simulated device); nothing outside the registry needs
to change for it to be validated, run and analysed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from crs_study.display import MODELS
from crs_study.errors import RenderError
from crs_study.geometry.layout import Layout
from crs_study.stimuli.targets import Bump

if TYPE_CHECKING:  # the strategies take the renderer's precomputed beam lines
    from crs_study.rendering.render import BeamGeometry

RenderFunction = Callable[[Layout, Bump, "BeamGeometry | None"], np.ndarray]

#: What the experimenter is asked to do before a block, by whether the beams are driven.
SETUP_PROMPTS = {True: "mount the skeleton (beams and boundary servos) for the {name} block",
                 False: "remove the skeleton: the {name} block shows the pixels and the "
                        "fabric alone"}


@dataclass(frozen=True)
class Condition:
    """One display condition (module docstring for each field's meaning).

    Parameters
    ----------
    name : the name protocols and datasets use (``conditions.names``, the ``condition``
        column): a non-empty string without whitespace.
    render : the strategy, ``render(layout, target, geometry) -> raw setpoints``.
    drives_beams : the skeleton is mounted and its boundary servos feed the beams.
    display_model : the display model the skin meets (a key of
        :data:`crs_study.display.MODELS`).
    fast_path : ``render`` equals the bump fast path for a plain bump.
    description : one line for help texts and listings.
    """

    name: str
    render: RenderFunction
    drives_beams: bool
    display_model: str
    fast_path: bool = False
    description: str = ""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name or self.name != "".join(
                self.name.split()):
            raise RenderError(f"a condition's name must be a non-empty string without "
                              f"whitespace, got {self.name!r}")
        if not callable(self.render):
            raise RenderError(f"condition {self.name!r}: render must be callable, got "
                              f"{self.render!r}")
        if self.display_model not in MODELS:
            raise RenderError(f"condition {self.name!r}: unknown display model "
                              f"{self.display_model!r}; known: {', '.join(sorted(MODELS))}")

    @property
    def setup_prompt(self) -> str:
        """What the experimenter does before a block of this condition (mount or remove the
        skeleton)."""
        return SETUP_PROMPTS[self.drives_beams].format(name=self.name)

    @property
    def benefit_side(self) -> float:
        """-1 on the pixels alone, +1 with the skeleton: the sign of a simulated
        participant's benefit draw in this condition's decision noise."""
        return 1.0 if self.drives_beams else -1.0


#: The registered conditions by name (:func:`register_condition`, :func:`get_condition`).
CONDITIONS: dict[str, Condition] = {}


def register_condition(condition: Condition) -> Condition:
    """Add ``condition`` to the registry (a name registered again is replaced) and return it.

    Every stage then knows it: protocols may list it in ``conditions.names``, the renderer
    draws it, the device checks, the simulated participant and the analysis treat it by what
    it says of itself.
    """
    if not isinstance(condition, Condition):
        raise RenderError(f"expected a Condition, got {condition!r}")
    CONDITIONS[condition.name] = condition
    return condition


def get_condition(name: str) -> Condition:
    """The registered condition ``name``; a one-line :class:`RenderError` naming the known
    ones otherwise."""
    condition = CONDITIONS.get(name) if isinstance(name, str) else None
    if condition is None:
        raise RenderError(f"unknown condition {name!r}; known: {', '.join(sorted(CONDITIONS))}")
    return condition
