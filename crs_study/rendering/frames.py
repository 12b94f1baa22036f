"""The one cache of rendered frames: a stimulus's setpoints, rendered once per device,
condition, feed cap and the wire's slack the cap leaves room for.

A digit's stimulus is the same in every trial (:mod:`crs_study.stimuli.stimulus`), so its
frames are rendered once and then served from here to everything that needs them: the
protocol's device checks (:mod:`crs_study.protocol.feasibility`), its wire budget
(:mod:`crs_study.protocol.wire`), the session runner, ``validate`` and ``device check``.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from crs_study.geometry.layout import layout_key
from crs_study.rendering.render import Renderer
from crs_study.stimuli.stimulus import Stimulus

#: key -> (read-only frames, whether any frame was clipped or capped)
_RENDERED: OrderedDict[tuple, tuple[np.ndarray, bool]] = OrderedDict()
_RENDERED_MAX = 512


def render_frames(stimulus: Stimulus, renderer: Renderer) -> np.ndarray:
    """Setpoints (n, n_actuators) of every frame, rendered once per stimulus, device,
    condition, feed cap and wire slack and then served from a cache (read-only array).

    The clamp policy is not part of the key: a stimulus that renders under ``"error"`` needs
    no clip, so its frames are those ``"clip"`` gives, and the device check (``"error"``) and
    the sessions (``"clip"``) share one rendering. Frames rendered under ``"clip"`` that had
    to be clipped are rendered again under ``"error"``, which raises at the first such frame.
    """
    key = (stimulus.key, layout_key(renderer.layout), renderer.condition, renderer.cap_feed,
           renderer.wire)
    cached = _RENDERED.get(key)
    if cached is not None and not (cached[1] and renderer.policy == "error"):
        _RENDERED.move_to_end(key)
        return cached[0]
    renderings = [renderer.render(stimulus.target(k)) for k in range(stimulus.n_frames)]
    frames = np.array([r.setpoints for r in renderings])
    frames.setflags(write=False)
    _RENDERED[key] = (frames, any(r.clamped for r in renderings))
    if len(_RENDERED) > _RENDERED_MAX:
        _RENDERED.popitem(last=False)
    return frames
