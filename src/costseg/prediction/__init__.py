"""The ``predict.py`` job: cost-based rules on a user's own images and videos (no labels)."""

from costseg.prediction.job import predict

__all__ = ["predict"]
