"""costseg: cost-based decision rules for semantic segmentation."""

__version__ = "0.1.0"
