"""The stimuli stage: what is drawn on the display, as a path of the bump over time.

* :mod:`~crs_study.stimuli.targets`: the raised-cosine bump of Eq. 7 and arc lengths along it;
* :mod:`~crs_study.stimuli.strokes`: a symbol's strokes (:class:`Glyph`), its size and
  sampling along them, for any set;
* :mod:`~crs_study.stimuli.symbol_set`: a stimulus set (:class:`StimulusSet`: symbols,
  strokes, response keys, BIDS task, chance rate) and its file format;
* :mod:`~crs_study.stimuli.digits`: the digit set, the default (strokes in
  ``crs_study/data/digits.toml`` or a protocol's own file);
* :mod:`~crs_study.stimuli.sets`: the sets by name (:func:`load_stimulus_set`: ``digits``,
  ``letters``, or a set file);
* :mod:`~crs_study.stimuli.stimulus`: a protocol's ``[stimulus]`` table (:class:`StimulusSpec`)
  and a symbol's stimulus, frame by frame (:func:`make_stimulus`).

Rendering those frames to setpoints is the next stage, :mod:`crs_study.rendering`.
"""

from crs_study.stimuli.digits import Digit, load_digits
from crs_study.stimuli.sets import DEFAULT_SET, default_set, load_stimulus_set, shipped_sets
from crs_study.stimuli.stimulus import Stimulus, StimulusSpec, make_stimulus, placement_centre
from crs_study.stimuli.strokes import Glyph, Symbol
from crs_study.stimuli.symbol_set import StimulusSet, load_set_file
from crs_study.stimuli.targets import Bump

__all__ = ["DEFAULT_SET", "Bump", "Digit", "Glyph", "Stimulus", "StimulusSet", "StimulusSpec",
           "Symbol", "default_set", "load_digits", "load_set_file", "load_stimulus_set",
           "make_stimulus", "placement_centre", "shipped_sets"]
