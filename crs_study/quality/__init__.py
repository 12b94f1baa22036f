"""Display quality: the paper's distortion criteria D_P, D_S and the CRS mechanics limits."""

from crs_study.quality.criteria import (
    DEFAULT_HEIGHT_MM,
    MAX_D_OVER_L,
    MIN_D_OVER_L,
    THEORY,
    Distortion,
    distortion,
    hull_distortion,
    theory,
)
from crs_study.quality.lattices import LATTICES, cell_rule, periodic_layout

__all__ = [
    "DEFAULT_HEIGHT_MM", "LATTICES", "MAX_D_OVER_L", "MIN_D_OVER_L", "THEORY", "Distortion",
    "cell_rule", "distortion", "hull_distortion", "periodic_layout", "theory",
]
