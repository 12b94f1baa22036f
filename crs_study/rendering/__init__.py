"""The rendering stage: a target surface to actuator setpoints, per experimental condition.

* :mod:`~crs_study.rendering.render`: the conditions (pixel-only, CRS) as strategies, the
  clamp policy and the feed cap (:class:`Renderer`);
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

from crs_study.rendering.frames import render_frames
from crs_study.rendering.render import CONDITIONS, Renderer, Rendering, register_condition

__all__ = ["CONDITIONS", "Renderer", "Rendering", "register_condition", "render_frames"]
