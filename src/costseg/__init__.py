"""costseg: cost-based decision rules for semantic segmentation."""

from importlib.resources import files

__version__ = "0.1.0"

# The package data: the LightningCLI configs and, in costs/, the cost matrices. They live once,
# in the repository's top-level configs/; src/costseg/configs is a link to it, so a checkout reads
# them there and the wheel carries them as files (read wherever the package is installed).
CONFIGS = files("costseg") / "configs"


def __getattr__(name: str):
    """``costseg.evaluate`` and ``costseg.predict``: :mod:`costseg.api`'s; ``costseg.Monitor``:
    :mod:`costseg.metrics.monitor`'s (docs/definitions.md §22); each imported on first use (they
    import torch)."""
    if name in ("evaluate", "predict"):
        from costseg import api

        return getattr(api, name)
    if name == "Monitor":
        from costseg.metrics.monitor import Monitor

        return Monitor
    raise AttributeError(f"module 'costseg' has no attribute {name!r}")
