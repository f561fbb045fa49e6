"""costseg: cost-based decision rules for semantic segmentation."""

from importlib.resources import files

__version__ = "0.1.0"

# The package data: the LightningCLI configs and, in costs/, the cost matrices (read wherever
# the package is installed).
CONFIGS = files("costseg") / "configs"
