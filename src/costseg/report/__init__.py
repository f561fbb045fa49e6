"""Reporting: the only part of costseg that draws or writes result files.

* :mod:`costseg.report.files`: atomic writers for text, JSON (NaN → ``null``), CSV, figures.
* :mod:`costseg.report.tables`: Markdown / console tables, the paper's table and numbers.
* :mod:`costseg.report.figures`: masks, FP/FN heatmaps; :mod:`costseg.report.cost_matrix`: cost
  matrices; :mod:`costseg.report.priors`: RoI map, priors.
* :mod:`costseg.report.ternary`: heatmaps over the value-space triangle, trade-offs per edge.
* :mod:`costseg.report.tensorboard`: the same tables, figures and masks in TensorBoard.

It knows nothing of the model or the data loading: it takes numbers, arrays and dict rows.
"""
