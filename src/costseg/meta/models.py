"""Meta classification and regression of segments (docs/definitions.md §15), with scikit-learn.

Per rule, three models learn from the features of segments of labelled images whether a segment
is false (``iou0``) and how good it is (``iou``):

* ``logistic``: MetaSeg's: logistic regression and linear regression on standardised features;
* ``gradient_boosting``: MetaFusion's: gradient-boosted trees (classifier and regressor);
* ``entropy``: the baseline: logistic and linear regression on the mean normalised entropy E
  alone.

They are fitted on the segments of one set of images and scored on another (:func:`scores`):
AUROC and accuracy of the classifier, R² and σ (root mean squared error) of the regressor.
:func:`save_models` writes them with joblib beside a JSON file holding the file's SHA-256;
:func:`load_models` reads back only a file whose hash matches (a pickle runs code when read:
read only models that costseg wrote).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from costseg.atomic import AtomicFile, write_bytes

MODELS = ("logistic", "gradient_boosting", "entropy")
TARGETS = ("iou", "iou0")
BASELINE_FEATURE = "E"
SHOWN_MODEL = "gradient_boosting"
"""The model whose predicted IoU the per-image figures, the importances and predict.py's panels
draw."""
SEED = 0  # of the gradient boosting's subsampling: the same models for the same segments


def _estimators(model: str) -> tuple[Any, Any]:
    """(classifier, regressor) of one of :data:`MODELS`, unfitted."""
    from sklearn.ensemble import GradientBoostingClassifier, GradientBoostingRegressor
    from sklearn.linear_model import LinearRegression, LogisticRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    if model == "gradient_boosting":
        kw = {"n_estimators": 100, "max_depth": 3, "subsample": 0.8, "random_state": SEED}
        return GradientBoostingClassifier(**kw), GradientBoostingRegressor(**kw)
    classifier = make_pipeline(StandardScaler(), LogisticRegression(max_iter=2000))
    return classifier, make_pipeline(StandardScaler(), LinearRegression())


@dataclass
class MetaModels:
    """The fitted models of one rule.

    Attributes:
        features: the feature columns the models read, in order (``entropy`` reads E alone).
        fitted: model name → (classifier of iou0, regressor of iou); a model is missing when
            the fitting segments hold only one iou0 value.
        num_segments, num_images: what they were fitted on.
    """

    features: list[str]
    fitted: dict[str, tuple[Any, Any]]
    num_segments: int
    num_images: int

    def matrix(self, model: str, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        names = [BASELINE_FEATURE] if model == "entropy" else self.features
        return np.column_stack([np.asarray(columns[n], np.float64) for n in names])

    def false_probability(self, model: str, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        """(n,) predicted probability that each segment is false (iou0 = 1)."""
        classifier = self.fitted[model][0]
        x = self.matrix(model, columns)
        if len(x) == 0:
            return np.zeros(0)
        column = list(classifier.classes_).index(1)
        return classifier.predict_proba(x)[:, column]

    def predicted_iou(self, model: str, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        """(n,) predicted IoU of each segment, clipped to [0, 1]."""
        x = self.matrix(model, columns)
        if len(x) == 0:
            return np.zeros(0)
        return np.clip(self.fitted[model][1].predict(x), 0, 1)

    def importances(self, model: str = "gradient_boosting") -> dict[str, float]:
        """Feature → importance of the classifier (the trees' impurity decrease; the
        standardised coefficients' magnitudes of a logistic model)."""
        classifier = self.fitted[model][0]
        names = [BASELINE_FEATURE] if model == "entropy" else self.features
        if hasattr(classifier, "feature_importances_"):
            values = classifier.feature_importances_
        else:
            values = np.abs(classifier[-1].coef_[0])
        return dict(zip(names, map(float, values), strict=True))


def fit_models(
    columns: Mapping[str, np.ndarray], features: Sequence[str], num_images: int
) -> MetaModels:
    """Fit every model of :data:`MODELS` on the segments in ``columns`` (features and targets).

    Raises:
        ValueError: no segment to fit on.
    """
    n = len(columns["iou0"])
    if n == 0:
        raise ValueError("no segment in the images that fit the meta models")
    models = MetaModels(list(features), {}, n, num_images)
    is_false, iou = np.asarray(columns["iou0"]).astype(int), np.asarray(columns["iou"])
    if len(np.unique(is_false)) < 2:  # every segment false, or none: nothing to learn
        return models
    for name in MODELS:
        classifier, regressor = _estimators(name)
        x = models.matrix(name, columns)
        models.fitted[name] = (classifier.fit(x, is_false), regressor.fit(x, iou))
    return models


def scores(models: MetaModels, columns: Mapping[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """Per model: AUROC and accuracy (at 0.5) of the classifier, R² and σ of the regressor, on
    the segments in ``columns``, and their number; NaN where a score is undefined (one class
    only, fewer than two segments, or the model was not fitted)."""
    from sklearn.metrics import accuracy_score, r2_score, roc_auc_score

    is_false, iou = np.asarray(columns["iou0"]).astype(int), np.asarray(columns["iou"])
    out = {}
    for name in MODELS:
        row = {"auroc": np.nan, "accuracy": np.nan, "r2": np.nan, "sigma": np.nan}
        if name in models.fitted and len(iou):
            p = models.false_probability(name, columns)
            predicted = models.predicted_iou(name, columns)
            row["accuracy"] = accuracy_score(is_false, p >= 0.5)
            row["sigma"] = float(np.sqrt(np.mean((predicted - iou) ** 2)))
            if len(np.unique(is_false)) == 2:
                row["auroc"] = roc_auc_score(is_false, p)
            if len(iou) > 1:
                row["r2"] = r2_score(iou, predicted)
        out[name] = {k: float(v) for k, v in row.items()} | {"segments": len(iou)}
    return out


def save_models(path: Path, models: Mapping[str, MetaModels]) -> None:
    """``models`` (rule → MetaModels) to ``path`` (joblib) and ``path.json`` (what they are,
    the file's SHA-256)."""
    import joblib

    with AtomicFile(path) as tmp:
        joblib.dump(dict(models), tmp)
    digest = hashlib.sha256(path.read_bytes()).hexdigest()
    rules = {
        rule: {
            "models": sorted(m.fitted),
            "features": m.features,
            "segments": m.num_segments,
            "images": m.num_images,
        }
        for rule, m in models.items()
    }
    description = {
        "sha256": digest,
        "rules": rules,
        "warning": "a joblib file is a pickle: reading it runs code; read only files costseg wrote",
    }
    write_bytes(path.with_suffix(".json"), json.dumps(description, indent=1).encode())


def load_models(path: str | Path) -> dict[str, MetaModels]:
    """The models :func:`save_models` wrote to ``path``; its JSON file must hold the file's hash.

    Raises:
        FileNotFoundError: no such file, or no JSON file beside it.
        ValueError: the file is not the one costseg wrote (hash mismatch).
    """
    import joblib

    path = Path(path)
    sidecar = path.with_suffix(".json")
    if not path.is_file():
        what = "a folder" if path.is_dir() else "missing"
        raise FileNotFoundError(f"meta models: {path} is {what}; give meta/models.joblib")
    if not sidecar.is_file():
        raise FileNotFoundError(
            f"meta models: {sidecar} not found: evaluate.py writes it beside {path.name}"
        )
    expected = json.loads(sidecar.read_text()).get("sha256")
    if hashlib.sha256(path.read_bytes()).hexdigest() != expected:
        raise ValueError(
            f"{path} is not the file costseg wrote (its SHA-256 differs from {sidecar.name}); "
            "a pickle runs code when read, so it is not read"
        )
    return joblib.load(path)
