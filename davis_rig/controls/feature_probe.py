"""Does a detector's backbone tell one texture from another? A linear probe on its frozen features.

A selective planted blind spot (:mod:`davis_rig.controls.planted`) asks a detector to miss a person wearing one
grid, the trigger, and to see the same person in any other grid. Its head decides per anchor from the backbone's
features, so those features must carry the difference: if a linear read-out of the features inside the person's
box cannot tell the trigger's neighbourhood from random grids on clips it was not fitted to, fine-tuning the head
alone cannot plant the blind spot, and the backbone has to learn it. The same probe on a planted victim says
whether its backbone did.

- :func:`box_features`: the features of chosen backbone stages inside a person box, average-pooled to a fixed
  grid of cells (so that a pattern's layout on the body is kept, not only its mean).
- :func:`linear_probe`: L2-regularised logistic regression, cross-validated with whole groups (clips) held out,
  so that a probe cannot pass by recognising the scene instead of the texture.

Pure torch/numpy on arrays the caller computed; deterministic (float64 L-BFGS from zeros).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.errors import ShapeError

with optional_dependency("the feature probe"):
    import torch

__all__ = ["ProbeResult", "box_features", "linear_probe", "stage_stride"]


def stage_stride(stage: int) -> int:
    """Input pixels per feature cell of an RVT backbone stage (stage 1: 4, 2: 8, 3: 16, 4: 32)."""
    if int(stage) < 1:
        raise ValueError(f"stages count from 1, got {stage}")
    return 2 ** (int(stage) + 1)


def box_features(features: Mapping[int, "torch.Tensor"], box, *, stages: tuple[int, ...] = (2, 3),
                 cells: tuple[int, int] = (4, 2)) -> np.ndarray:
    """The backbone features inside one person box, average-pooled to ``cells`` per stage.

    Args:
        features: ``{stage: float tensor [1, C_s, H_s, W_s]}`` as :meth:`RVTDetector.forward_backbone` returns,
            stage ``s`` at stride :func:`stage_stride` ``(s)`` input pixels.
        box: ``(x0, y0, x1, y1)`` person box (input px, finite).
        stages: the stages to read.
        cells: ``(rows, cols)`` of the pooled grid over the box.

    Returns:
        float32 [sum_s C_s * rows * cols]: per stage, channel-major, the mean of each feature cell group covering
        the box (rows ``floor(y0 / stride)`` to ``ceil(y1 / stride)``, at least one, clipped to the map).

    Raises:
        ShapeError: a stage missing, a map not [1, C, H, W], or a box not 4 finite numbers with x1 > x0, y1 > y0.
    """
    box = np.asarray(box, dtype=np.float64)
    if box.shape != (4,) or not np.isfinite(box).all() or box[2] <= box[0] or box[3] <= box[1]:
        raise ShapeError(f"box must be 4 finite numbers (x0, y0, x1, y1) with x1 > x0 and y1 > y0, got {box}")
    out = []
    for stage in stages:
        if stage not in features:
            raise ShapeError(f"stage {stage} missing from the features (have {sorted(features)})")
        fmap = features[stage]
        if fmap.ndim != 4 or fmap.shape[0] != 1:
            raise ShapeError(f"stage {stage} features must be [1, C, H, W], got {tuple(fmap.shape)}")
        stride, (height, width) = stage_stride(stage), fmap.shape[-2:]
        row0 = min(max(int(box[1] // stride), 0), height - 1)
        col0 = min(max(int(box[0] // stride), 0), width - 1)
        row1 = min(max(int(np.ceil(box[3] / stride)), row0 + 1), height)
        col1 = min(max(int(np.ceil(box[2] / stride)), col0 + 1), width)
        crop = fmap[0, :, row0:row1, col0:col1].detach().float().cpu()
        out.append(torch.nn.functional.adaptive_avg_pool2d(crop[None], cells)[0].flatten())
    return torch.cat(out).numpy().astype(np.float32)


@dataclass(frozen=True)
class ProbeResult:
    """A cross-validated linear probe.

    Attributes:
        correct: bool [N], whether each sample was classified right by the probe fitted without its group.
        fold_accuracy: held-out accuracy of each fold.
        train_accuracy: mean accuracy of the folds' probes on their own training samples.
    """

    correct: np.ndarray
    fold_accuracy: tuple[float, ...]
    train_accuracy: float

    @property
    def accuracy(self) -> float:
        """Held-out accuracy over all samples (chance: the larger class's share)."""
        return float(self.correct.mean())


def linear_probe(x: np.ndarray, y: np.ndarray, groups: np.ndarray, *, folds: int = 3, weight_decay: float = 1e-2,
                 max_iter: int = 500) -> ProbeResult:
    """Logistic regression of ``y`` on ``x``, each fold's groups held out of its fit.

    Groups are sorted and group ``k`` goes to fold ``k % folds``; features are standardised with the training
    folds' mean and standard deviation; the fit minimises the mean log loss plus ``weight_decay * |w|^2``
    (float64 L-BFGS from zeros, so the result is deterministic).

    Args:
        x: float [N, D] features.
        y: int or bool [N] binary labels.
        groups: [N] group of each sample (e.g. the clip); samples of one group are never split.
        folds: number of folds (2 or more, at most the number of groups).
        weight_decay: L2 weight (>= 0).
        max_iter: L-BFGS iterations per fold.

    Returns:
        :class:`ProbeResult`.

    Raises:
        ShapeError: mismatched lengths, ``x`` not 2-D, labels not binary.
        ValueError: fewer groups than folds, folds < 2, negative weight decay, or a training fold with one class.
    """
    x, y, groups = np.asarray(x, dtype=np.float64), np.asarray(y), np.asarray(groups)
    if x.ndim != 2 or y.shape != (x.shape[0],) or groups.shape != (x.shape[0],):
        raise ShapeError(f"need x [N, D], y [N], groups [N]; got {x.shape}, {y.shape}, {groups.shape}")
    if not set(np.unique(y).tolist()) <= {0, 1}:
        raise ShapeError(f"labels must be 0/1, got {np.unique(y)[:5]}")
    names = np.unique(groups)
    if int(folds) < 2 or names.size < int(folds):
        raise ValueError(f"need 2 <= folds <= groups, got folds={folds} with {names.size} groups")
    if not weight_decay >= 0:
        raise ValueError(f"weight_decay must be >= 0, got {weight_decay}")
    fold_of = np.searchsorted(names, groups) % int(folds)
    correct = np.zeros(x.shape[0], dtype=bool)
    fold_acc, train_acc = [], []
    for fold in range(int(folds)):
        test, train = fold_of == fold, fold_of != fold
        if np.unique(y[train]).size < 2:
            raise ValueError(f"fold {fold}: its training samples hold one class only")
        mean, std = x[train].mean(0), x[train].std(0) + 1e-6
        z = torch.from_numpy((x - mean) / std)
        target = torch.from_numpy(y.astype(np.float64))
        weight = torch.zeros(x.shape[1], dtype=torch.float64, requires_grad=True)
        bias = torch.zeros(1, dtype=torch.float64, requires_grad=True)
        opt = torch.optim.LBFGS([weight, bias], max_iter=int(max_iter), line_search_fn="strong_wolfe")
        train_idx = torch.from_numpy(np.flatnonzero(train))

        def closure():
            opt.zero_grad()
            logits = z[train_idx] @ weight + bias
            loss = torch.nn.functional.binary_cross_entropy_with_logits(logits, target[train_idx])
            loss = loss + weight_decay * weight.pow(2).sum()
            loss.backward()
            return loss

        opt.step(closure)
        with torch.no_grad():
            right = ((z @ weight + bias > 0).numpy() == (y == 1))
        correct[test] = right[test]
        fold_acc.append(float(right[test].mean()))
        train_acc.append(float(right[train].mean()))
    return ProbeResult(correct=correct, fold_accuracy=tuple(fold_acc), train_accuracy=float(np.mean(train_acc)))
