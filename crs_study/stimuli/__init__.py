"""The stimuli stage: what is drawn on the display, as a path of the bump over time.

* :mod:`~crs_study.stimuli.targets`: the raised-cosine bump of Eq. 7 and arc lengths along it;
* :mod:`~crs_study.stimuli.digits`: the digits' strokes (shipped in ``crs_study/data/digits.toml``
  or a protocol's own file) and sampling along them;
* :mod:`~crs_study.stimuli.stimulus`: a protocol's ``[stimulus]`` table (:class:`StimulusSpec`)
  and a digit's stimulus, frame by frame (:func:`make_stimulus`).

Rendering those frames to setpoints is the next stage, :mod:`crs_study.rendering`.
"""

from crs_study.stimuli.digits import Digit, load_digits
from crs_study.stimuli.stimulus import Stimulus, StimulusSpec, make_stimulus, placement_centre
from crs_study.stimuli.targets import Bump

__all__ = ["Bump", "Digit", "Stimulus", "StimulusSpec", "load_digits", "make_stimulus",
           "placement_centre"]
