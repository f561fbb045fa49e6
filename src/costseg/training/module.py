"""The LightningModule: a segmentation network trained with a loss of the config, validated
under cost rules.

The network is any ``nn.Module`` mapping normalised images to logits; a config names it as
``model.net`` (``class_path`` / ``init_args``, LightningCLI's own mechanism), and the checkpoint
records that entry (``hparams["net"]``), from which :mod:`costseg.networks.costseg` rebuilds it.

Training minimises ``model.loss`` (:mod:`costseg.training.losses`: cross-entropy by default,
ignore index 255; the checkpoint records its entry as ``hparams["loss"]``), logged as
``train/loss`` with its terms (``train/cross_entropy``, ...). Validation takes the softmax and swaps
``argmax`` for the configured decision rules (robotistic by default, i.e. argmax), all rules
in one pass (the step of :mod:`costseg.metrics.scoring`, shared with evaluation), and logs mIoU,
per-class IoU and person/building recall in the street RoI per rule (and the share of pixels a
rule with a defer row deferred). The pixel-wise priors (and so the RoI map) travel inside the
checkpoint. Side outputs (masks in TensorBoard) are callbacks (:mod:`costseg.training.callbacks`).
"""

from __future__ import annotations

from typing import Any, Literal

import lightning as L
import torch
from torch import nn

from costseg.checkpoints import CHECKPOINT_KEY
from costseg.classes import CLASS_NAMES, class_index
from costseg.data.prior_maps import PriorMaps
from costseg.metrics import CalibrationError
from costseg.metrics.names import PIXEL_RATES
from costseg.metrics.scoring import GroupMetrics, score_batch
from costseg.models.entries import module_entry
from costseg.networks.base import IMAGENET_MEAN, IMAGENET_STD, at_input_size, normalised
from costseg.rules import parse_rules, rules_group
from costseg.training.losses import CrossEntropy, SegmentationLoss, batch_mean


class SegmentationModule(L.LightningModule):
    """A segmentation network with cost-based validation.

    Args:
        net: (B, 3, H, W) ImageNet-normalised images → (B, num_classes, h, w) logits (smaller
            logits are resized to the input), e.g. `costseg.models.deeplabv3plus.DeepLabV3Plus`;
            in a config, ``model.net`` with ``class_path`` and ``init_args`` (``num_classes`` is
            linked to this module's); a builder function or a network returning a dict goes
            through `costseg.models.adapter.NetworkAdapter`.
            train.py records the config's entry; a network built in Python is recorded from
            its ``init_args`` attribute (:func:`costseg.models.entries.module_entry`).
        num_classes: output classes (19 Cityscapes train classes).
        loss: the training loss, e.g. `costseg.training.losses.FocalLoss`; in a config,
            ``model.loss`` with ``class_path`` and ``init_args`` (docs/definitions.md §16).
            None = cross-entropy.
        optimizer: ``sgd`` (momentum, Nesterov off) or ``adamw``.
        lr: peak learning rate, decayed by the poly schedule ``(1 - step/total) ** poly_power``.
        momentum: SGD momentum.
        weight_decay: L2 / decoupled weight decay.
        poly_power: exponent of the poly schedule.
        warmup_steps: steps over which the learning rate rises linearly to ``lr`` before the
            poly decay (0 = none); lets a short schedule start at a high rate.
        val_costs: decision rules applied in validation (names as for ``evaluate.py --cost``;
            a cost file with a defer row defers pixels, docs/definitions.md §14).
        prior_sigma: Gaussian smoothing (pixels) of the pixel-wise priors; None = the
            default 80 · H / 1024 (docs/definitions.md §3) for labels of height H.
        channels_last: run the network in channels-last memory format (faster convolutions
            on CPUs and on GPUs with tensor cores).
    """

    def __init__(
        self,
        net: nn.Module,
        num_classes: int = 19,
        loss: SegmentationLoss | None = None,
        optimizer: Literal["sgd", "adamw"] = "sgd",
        lr: float = 0.01,
        momentum: float = 0.9,
        weight_decay: float = 1e-4,
        poly_power: float = 0.9,
        warmup_steps: int = 0,
        val_costs: tuple[str, ...] = ("robotistic",),
        prior_sigma: float | None = None,
        channels_last: bool = True,
    ) -> None:
        super().__init__()
        _check_hyperparameters(lr, momentum, weight_decay, poly_power, warmup_steps)
        self.save_hyperparameters(ignore=["net", "loss"])
        self.hparams["net"] = module_entry(net)  # train.py records the config's own entry
        self.net = net
        self.loss = loss if loss is not None else CrossEntropy()
        self.loss.for_classes(CLASS_NAMES[:num_classes])
        self.hparams["loss"] = module_entry(self.loss)
        if channels_last:
            self.net = self.net.to(memory_format=torch.channels_last)
        self.rules = rules_group(parse_rules(val_costs, CLASS_NAMES[:num_classes]))
        self.val_metrics = GroupMetrics(self.rules, num_classes)
        self.val_ece = CalibrationError(num_classes)
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), False)
        self.priors = None  # (N, H, W) at label resolution, set before fit
        self.data_config: dict[str, Any] | None = None  # how to rebuild the data, for evaluation
        self.priors_info: dict[str, Any] | None = None  # how the priors were estimated

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """(B, 3, H, W) uint8 RGB → (B, N, H, W) logits (a network's smaller logits resized
        bilinearly to the input, as evaluation does)."""
        x = normalised(images, self.mean, self.std, 255.0, self.hparams.channels_last)
        return at_input_size(self.net(x), images)

    @property
    def priors(self) -> torch.Tensor | None:
        """(N, H, W) pixel-wise priors at label resolution (None before they are computed)."""
        return self._priors.priors

    @priors.setter
    def priors(self, value: torch.Tensor | None) -> None:
        self._priors = PriorMaps(value, CLASS_NAMES[: self.hparams.num_classes])
        self._loss_priors: torch.Tensor | None = None

    def loss_priors(self, size: tuple[int, int]) -> torch.Tensor | None:
        """The priors the loss uses (``loss.uses_priors``) for labels of ``size``, on the
        module's device: global (N,) or pixel-wise (N, H, W) mirror-averaged, since training
        flips half the images; None for a loss without priors."""
        kind = self.loss.uses_priors
        if kind is None:
            return None
        if self.priors is None:
            raise ValueError(f"model.loss {type(self.loss).__name__} needs the training priors")
        if kind == "pixel" and tuple(self.priors.shape[1:]) != tuple(size):
            raise ValueError(
                f"pixel-wise priors are {tuple(self.priors.shape[1:])} but the training labels "
                f"are {tuple(size)} (random crops have no fixed location): use priors: global"
            )
        if self._loss_priors is None or self._loss_priors.device != self.device:
            pi = self.priors.double()
            pi = pi.mean((1, 2)) if kind == "global" else (pi + pi.flip(-1)) / 2
            self._loss_priors = (pi / pi.sum(0, keepdim=True)).float().to(self.device)
        return self._loss_priors

    def batch_loss(
        self, logits: torch.Tensor, labels: torch.Tensor
    ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The configured loss of a batch and its terms, means over every process's valid
        pixels (:func:`costseg.training.losses.batch_mean`)."""
        priors = self.loss_priors(tuple(labels.shape[-2:]))
        return batch_mean(self.loss(logits, labels, priors))

    def training_step(self, batch: tuple[torch.Tensor, torch.Tensor], batch_idx: int):
        images, labels = batch
        loss, terms = self.batch_loss(self(images), labels)
        self.log("train/loss", loss, prog_bar=True, sync_dist=True)
        for name, value in terms.items():
            self.log(f"train/{name}", value, sync_dist=True)
        return loss

    def validation_step(self, batch: tuple[torch.Tensor, torch.Tensor], batch_idx: int) -> dict:
        images, labels = batch
        logits = self(images)
        loss, _ = self.batch_loss(logits, labels)
        self.log("val/loss", loss, sync_dist=True)
        priors, roi = self._priors.at(tuple(labels.shape[-2:]))
        if priors is not None:
            priors, roi = priors.to(self.device), roi.to(self.device)
        probs = logits.float().softmax(1)
        self.val_ece.update(probs, labels)
        preds = score_batch(self.rules, self.val_metrics, probs, labels, priors, roi)
        return {"preds": preds, "names": self.rules.names}

    def on_validation_epoch_end(self) -> None:
        out = self.val_metrics.compute()["pixels"]
        self.val_metrics.reset()
        self.log("val/miou", out["miou"][0].float(), prog_bar=True)
        calibration = self.val_ece.compute()
        for score in ("ece", "nll", "brier"):
            self.log(f"val/{score}", calibration[score].float())
        self.val_ece.reset()
        names = CLASS_NAMES[: self.hparams.num_classes]
        person, building = class_index("person", names), class_index("building", names)
        for k, rule in enumerate(self.rules.names):
            self.log(f"val/miou/{rule}", out["miou"][k].float())
            for c, name in enumerate(names):
                self.log(f"val/iou/{rule}/{name}", out["iou"][k, c].float())
            for c, name in ((person, "person"), (building, "building")):
                for metric in PIXEL_RATES:
                    value = out[metric][k, 1, c].float()
                    self.log(f"val/{metric}_street/{rule}/{name}", value)
            if self.rules.rules[k].defers:  # a deferred pixel is a false negative in IoU
                self.log(f"val/deferred_rate/{rule}", out["deferred_rate"][k, 0].float())

    def configure_optimizers(self):
        h = self.hparams
        if h.optimizer == "sgd":
            opt = torch.optim.SGD(
                self.parameters(), lr=h.lr, momentum=h.momentum, weight_decay=h.weight_decay
            )
        else:
            opt = torch.optim.AdamW(self.parameters(), lr=h.lr, weight_decay=h.weight_decay)
        total = max(1, int(self.trainer.estimated_stepping_batches))

        def factor(step: int) -> float:
            warmup = min(1.0, (step + 1) / h.warmup_steps) if h.warmup_steps else 1.0
            return warmup * max(0.0, 1 - step / total) ** h.poly_power

        schedule = torch.optim.lr_scheduler.LambdaLR(opt, factor)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}

    def on_save_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        checkpoint[CHECKPOINT_KEY] = {
            "class_names": list(CLASS_NAMES[: self.hparams.num_classes]),
            "priors": None if self.priors is None else self.priors.cpu(),
            "data": self.data_config,
            "priors_info": self.priors_info,
        }

    def on_load_checkpoint(self, checkpoint: dict[str, Any]) -> None:
        extra = checkpoint.get(CHECKPOINT_KEY, {})
        self.priors = extra.get("priors")
        self.data_config = extra.get("data")
        self.priors_info = extra.get("priors_info")


def _check_hyperparameters(
    lr: float, momentum: float, weight_decay: float, power: float, warmup_steps: int
) -> None:
    """Refuse values no optimiser accepts, before anything is computed (one line each)."""
    if not lr > 0:
        raise ValueError(f"--model.lr must be > 0, got {lr}")
    if not 0 <= momentum < 1:
        raise ValueError(f"--model.momentum must lie in [0, 1), got {momentum}")
    if not weight_decay >= 0:
        raise ValueError(f"--model.weight_decay must be >= 0, got {weight_decay}")
    if not power >= 0:
        raise ValueError(f"--model.poly_power must be >= 0, got {power}")
    if not (isinstance(warmup_steps, int) and warmup_steps >= 0):
        raise ValueError(f"--model.warmup_steps must be an integer >= 0, got {warmup_steps}")
