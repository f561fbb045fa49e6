"""The CPU's compiled kernels (numba), behind the ``numba`` path (:mod:`.numba_path`)."""

VERTICES = 3  # the mixture kernel's most vertex matrices (a sweep's triangle); fewer: padded
