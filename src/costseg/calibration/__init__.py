"""Calibrated probabilities and guaranteed choices (docs/definitions.md §6, §7).

:mod:`~costseg.calibration.scaling` fits temperature and vector scaling,
:mod:`~costseg.calibration.sample` draws the pixels they are fitted on, and
:mod:`~costseg.calibration.guarantee` picks a value system with a Learn-then-Test guarantee.
"""

from costseg.calibration.scaling import Scaling, fit_temperature, fit_vector_scaling

__all__ = ["Scaling", "fit_temperature", "fit_vector_scaling"]
