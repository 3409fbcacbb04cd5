"""The attack step's detector part as one fixed-shape function, to record as a CUDA graph or compile.

One step of :func:`~davis_rig.attack.step.attack_loss` has two parts:

1. **texture → RVT input** (variable shapes): per clip, the texture lookup and compose on the person's active box
   and the differentiable V2E there (:func:`~davis_rig.attack.step.clip_histograms`), stacked into
   ``x`` float [W, B, 20, 240, 304] (W windows, B clips);
2. **RVT input → loss** (fixed shapes for a whole run): zero-pad to the detector's input, RVT over the W windows
   with recurrent states (batched over the B clips), ``L_adv`` (:func:`~davis_rig.attack.loss.adversarial_loss`).

Part 2 is most of a step (measured on an H200: RVT-B forward 36 ms + backward 47 ms of a 92 ms step, 1 clip) and
is launch-bound on a GPU (RVT-T costs what RVT-B does), so it is what a CUDA graph or ``torch.compile`` speeds up.
:class:`DetectorLoss` is that part alone: its input shapes are the same at every step, it has no data-dependent
control flow and no host↔device copy, so it can be recorded once — forward and backward —
with ``torch.cuda.make_graphed_callables`` and replayed with one launch per pass. :class:`FixedShapeAttackLoss`
is a drop-in for ``attack_loss(grid, clips, detector, config)`` that runs part 1 as before and part 2 through
:class:`DetectorLoss` in one of three modes:

* ``"eager"``: the module as is — the same operations in the same order as ``attack_loss``, so the loss and the
  texture gradient are bit-identical to it (tested on CPU);
* ``"cuda_graph"``: ``torch.cuda.make_graphed_callables`` on the first call (the input buffers become static;
  CUDA only);
* ``"compile"``: ``torch.compile(dynamic=False)``, with ``mode="reduce-overhead"`` (CUDA graphs) on CUDA.

Equal-shaped inputs are required for the graph modes: the same ``clips_per_step`` at every step (the attack's
pool sampling keeps it) and the same windows per clip.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from davis_rig._lazy import optional_dependency
from davis_rig.attack.config import DETECTOR_STEPS
from davis_rig.attack.loss import AdversarialLoss, adversarial_loss, anchor_cells, anchors_on_boxes
from davis_rig.errors import ConfigError, ShapeError

with optional_dependency("the attack"):
    import torch

__all__ = ["STEP_MODES", "DetectorLoss", "FixedShapeAttackLoss"]

#: How :class:`FixedShapeAttackLoss` runs the detector part (``AttackConfig.detector_step``).
STEP_MODES = DETECTOR_STEPS


class DetectorLoss(torch.nn.Module):
    """RVT over the windows + ``L_adv``: ``x`` [W, B, 20, h, w] (and person boxes) → (total, obj, cls, count).

    Args:
        detector: the frozen :class:`~davis_rig.models.rvt.detector.RVTDetector` (eval mode, no parameter grads).
        config: the :class:`~davis_rig.attack.config.AttackConfig` (loss weights, reduction, box margin,
            precision: ``"bf16"`` autocasts the detector, with the autocast cache off as CUDA graphs need).

    ``forward(x)`` or, with ``config.box_margin_px`` set or ``config.loss_anchors == "person"``, ``forward(x, boxes)``
    (boxes float [W, B, 4] in input pixels, NaN = no person) returns the :class:`~davis_rig.attack.loss.AdversarialLoss` fields as a tuple of
    0-dim tensors ``(total, obj, cls, num_anchors)``.
    """

    def __init__(self, detector, config):
        super().__init__()
        self.detector = detector
        self.lambda_obj = float(config.lambda_obj)
        self.lambda_cls = float(config.lambda_cls)
        self.reduction = config.loss_reduction
        self.box_margin_px = config.box_margin_px
        self.bf16 = config.precision == "bf16"
        self.person_anchors = config.loss_anchors == "person"
        device = next(detector.parameters()).device
        self.register_buffer("cells", anchor_cells(detector.config.in_res_hw, detector.config.head_strides,
                                                   device=device), persistent=False)

    def forward(self, x: "torch.Tensor", boxes: "torch.Tensor | None" = None) -> tuple:
        from davis_rig.models.rvt.detector import pad_to_input

        decoded, states = [], None
        with torch.autocast(device_type=x.device.type, dtype=torch.bfloat16, enabled=self.bf16,
                            cache_enabled=False):
            for w in range(x.shape[0]):
                out, states = self.detector(pad_to_input(x[w], self.detector.config.in_res_hw), states)
                decoded.append(out.float())
        on_person = anchors_on_boxes(self.cells, boxes) if self.person_anchors else None
        loss = adversarial_loss(decoded, self.lambda_obj, self.lambda_cls,
                                boxes=boxes if self.box_margin_px is not None else None,
                                box_margin_px=self.box_margin_px or 0.0, reduction=self.reduction,
                                anchor_mask=on_person)
        return loss.total, loss.obj, loss.cls, loss.num_anchors


class FixedShapeAttackLoss:
    """``attack_loss`` with its detector part (:class:`DetectorLoss`) eager, CUDA-graphed or compiled.

    ``FixedShapeAttackLoss(detector, config, mode)(grid, clips)`` returns what
    ``attack_loss(grid, clips, detector, config)`` returns; backward through it reaches the texture the same way.

    Args:
        detector: the frozen detector (its device is where part 2 runs).
        config: :class:`~davis_rig.attack.config.AttackConfig`.
        mode: one of :data:`STEP_MODES`.

    Raises:
        ConfigError: unknown mode, or ``"cuda_graph"`` with a detector that is not on a CUDA device (field
            ``detector_step``).
    """

    def __init__(self, detector, config, mode: str = "eager"):
        if mode not in STEP_MODES:
            raise ConfigError("detector_step", f"expected one of {STEP_MODES}, got {mode!r}")
        self.device = next(detector.parameters()).device
        if mode == "cuda_graph" and self.device.type != "cuda":
            raise ConfigError("detector_step", f"'cuda_graph' records a CUDA graph: the detector is on {self.device}, "
                                               "not CUDA (--device cuda)")
        self.config = config
        self.mode = mode
        self.module = DetectorLoss(detector, config)
        self._run = self.module if mode == "eager" else None
        self._shapes = None

    def _prepare(self, args: tuple) -> None:
        """Build the graphed/compiled callable for the shapes of ``args`` (first call)."""
        if self.mode == "cuda_graph":
            samples = tuple(a.detach().clone().requires_grad_(a.requires_grad) for a in args)
            self._run = torch.cuda.make_graphed_callables(self.module, samples)
        else:
            options = {"mode": "reduce-overhead"} if self.device.type == "cuda" else {}
            self._run = torch.compile(self.module, dynamic=False, **options)

    def __call__(self, grid: "torch.Tensor", clips: Sequence) -> AdversarialLoss:
        """``L_adv`` of ``grid`` over ``clips`` (see :func:`~davis_rig.attack.step.attack_loss`).

        Raises:
            ShapeError: a graph mode gets inputs of other shapes than at its first call.
        """
        from davis_rig.attack.step import clip_histograms

        config = self.config
        x = torch.stack([clip_histograms(grid, c, config.v2e_mode, config.v2e_binning, config.v2e_gradient)
                         for c in clips], dim=1).to(self.device)
        args = (x,)
        if config.box_margin_px is not None or config.loss_anchors == "person":
            args += (torch.as_tensor(np.stack([c.boxes for c in clips], axis=1), device=self.device),)
        shapes = tuple(tuple(a.shape) for a in args)
        if self._run is None:
            self._prepare(args)
            self._shapes = shapes
        elif self.mode != "eager" and shapes != self._shapes:
            raise ShapeError(f"the {self.mode} detector loss was built for inputs {self._shapes}, got {shapes}: "
                             "keep clips_per_step and the windows per clip fixed")
        return AdversarialLoss(*self._run(*args))
