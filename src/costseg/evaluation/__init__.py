"""The ``evaluate.py`` job: options → checks → plan → one pass over the images → results.

:mod:`~costseg.evaluation.checks` validates options before anything heavy,
:mod:`~costseg.evaluation.plan` opens the source and data and claims the output folder,
:mod:`~costseg.evaluation.run` runs the pass, and :mod:`~costseg.evaluation.held_out` fits and
certifies on the calibration images.
"""
