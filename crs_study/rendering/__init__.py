"""The rendering stage: a target surface to actuator setpoints, per experimental condition.

* :mod:`~crs_study.rendering.conditions`: what a display condition means
  (:class:`Condition`: its strategy, whether it drives the beams, the display model the skin
  meets, its fast path) and the registry every stage asks (:func:`get_condition`);
* :mod:`~crs_study.rendering.render`: the shipped conditions (pixel-only, CRS), the clamp
  policy and the feed cap (:class:`Renderer`);
* :mod:`~crs_study.rendering.feed_cap`: the feed cap's rules, with room for what the boards
  hold (whole-us pulses, the write policy's dead-band: :class:`~.feed_cap.WireSlack`);
* :mod:`~crs_study.rendering.bump_path`: a bump's setpoints with few numpy calls (the live
  link's and the sessions' path for the built-in conditions);
* :mod:`~crs_study.rendering.frames`: the one cache of a stimulus's rendered frames
  (:func:`render_frames`).

The display models (:mod:`crs_study.display`, setpoints to the surface the skin meets) sit
below this stage (the feed cap asks the compressed beam for its longest stable shape); the
quality criteria (:mod:`crs_study.quality`) sit above it.
"""

from crs_study.rendering.conditions import (
    CONDITIONS,
    Condition,
    get_condition,
    register_condition,
)
from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import Renderer, Rendering

__all__ = ["CONDITIONS", "Condition", "Renderer", "Rendering", "get_condition",
           "register_condition", "render_frames"]
