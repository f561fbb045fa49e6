"""Training: the LightningModule, its callbacks and the ``train.py`` job."""
