"""The GPU's kernel (Triton), behind the ``triton`` path (:mod:`.triton_path`)."""
