"""Calibrated probabilities and guaranteed choices (docs/definitions.md §6, §7, §18).

:mod:`~costseg.calibration.scaling` fits temperature and vector scaling,
:mod:`~costseg.calibration.sample` draws the pixels they are fitted on,
:mod:`~costseg.calibration.guarantee` picks a value system with a Learn-then-Test guarantee, and
:mod:`~costseg.calibration.conformal` builds prediction sets anchored on a rule and sizes them
by conformal risk control.
"""

from costseg.calibration.scaling import Scaling, fit_temperature, fit_vector_scaling

__all__ = ["Scaling", "fit_temperature", "fit_vector_scaling"]
