"""RVT detector: recurrent backbone + PAFPN + YOLOX head with explicit LSTM states.

``RVTDetector(config).state_dict()`` has exactly the keys of an official Gen1 checkpoint's
``ckpt["state_dict"]`` with the Lightning ``mdl.`` prefix removed.

Example:
    >>> import torch
    >>> from davis_rig.models.rvt import RVTConfig
    >>> from davis_rig.models.rvt.detector import RVTDetector, pad_to_input
    >>> model = RVTDetector(RVTConfig.mini()).eval()
    >>> hist = torch.zeros(1, 20, 240, 304)  # counts 0..10 from events/histogram.py
    >>> decoded, states = model(pad_to_input(hist))
    >>> decoded.shape
    torch.Size([1, 1680, 7])
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from davis_rig.errors import ShapeError
from davis_rig.models.rvt._torch import F, nn, torch
from davis_rig.models.rvt.backbone import LstmState, RVTBackbone
from davis_rig.models.rvt.config import GEN1_INPUT_HW, RVTConfig
from davis_rig.models.rvt.fpn import PAFPN
from davis_rig.models.rvt.head import YOLOXHead
from davis_rig.types import RVT_HW


def pad_to_input(hist, in_res_hw: tuple[int, int] = GEN1_INPUT_HW) -> torch.Tensor:
    """Zero-pad a histogram at the bottom and right to the network input size (official ``InputPadderFromShape``).

    Args:
        hist: uint8 or float counts [B, C, H, W] (torch tensor or numpy array), H ≤ in_res_hw[0],
            W ≤ in_res_hw[1]; typically [B, 20, 240, 304].
        in_res_hw: padded (height, width), px.

    Returns:
        float32 (or the input's floating dtype) tensor [B, C, in_res_hw[0], in_res_hw[1]]; the input is not modified.

    Raises:
        ShapeError: not 4-D, or larger than ``in_res_hw``.
    """
    if not isinstance(hist, torch.Tensor):
        hist = torch.from_numpy(np.ascontiguousarray(hist))
    if hist.ndim != 4:
        raise ShapeError(f"pad_to_input: expected [B, C, H, W], got shape {tuple(hist.shape)}")
    height, width = int(hist.shape[-2]), int(hist.shape[-1])
    pad_h, pad_w = in_res_hw[0] - height, in_res_hw[1] - width
    if pad_h < 0 or pad_w < 0:
        raise ShapeError(
            f"pad_to_input: expected H ≤ {in_res_hw[0]} and W ≤ {in_res_hw[1]}, got shape {tuple(hist.shape)}"
        )
    if not hist.is_floating_point():
        hist = hist.to(torch.float32)
    if pad_h == 0 and pad_w == 0:
        return hist
    return F.pad(hist, [0, pad_w, 0, pad_h])


class RVTDetector(nn.Module):
    """The RVT Gen1 detector with explicit recurrent state (submodules ``backbone``, ``fpn``, ``yolox_head``).

    One call = one 50 ms window: ``decoded, states = model(x, states)``. The model is built in train mode as
    any ``nn.Module``; call ``.eval()`` (``load_detector`` does) so BatchNorm uses its running statistics.

    Args:
        config: the architecture (:class:`RVTConfig`).
    """

    def __init__(self, config: RVTConfig):
        super().__init__()
        self.config = config
        self.backbone = RVTBackbone(config)
        self.fpn = PAFPN(config.fpn_in_channels, config.fpn_num_bottlenecks)
        self.yolox_head = YOLOXHead(config.num_classes, config.head_strides, config.fpn_in_channels)

    # ------------------------------------------------------------------ states
    def initial_states(self, batch: int = 1, device=None, dtype=None) -> list[LstmState]:
        """Zero LSTM states (start of a sequence).

        Args:
            batch: batch size B.
            device, dtype: default: those of the model's parameters.

        Returns:
            4 × (h, c), zeros [B, C_s, H_s, W_s] (shapes from ``config.state_shapes``).
        """
        reference = next(self.parameters())
        device = reference.device if device is None else device
        dtype = reference.dtype if dtype is None else dtype
        return [
            (torch.zeros(h_shape, device=device, dtype=dtype), torch.zeros(c_shape, device=device, dtype=dtype))
            for h_shape, c_shape in self.config.state_shapes(batch)
        ]

    def _check_input(self, x: torch.Tensor) -> None:
        expected = (self.config.input_channels, *self.config.in_res_hw)
        if not isinstance(x, torch.Tensor):
            raise ShapeError(f"RVTDetector input: expected a torch.Tensor [B, {expected[0]}, {expected[1]}, "
                             f"{expected[2]}], got {type(x).__name__}")
        if x.ndim != 4 or tuple(int(v) for v in x.shape[1:]) != expected:
            raise ShapeError(
                f"RVTDetector input: expected [B, {expected[0]}, {expected[1]}, {expected[2]}] (padded, see "
                f"pad_to_input), got {tuple(x.shape)}"
            )
        if not x.is_floating_point():
            raise ShapeError(f"RVTDetector input: expected a floating tensor, got dtype {x.dtype}")

    def _check_states(self, states: Sequence[LstmState], batch: int) -> list[LstmState]:
        expected = self.config.state_shapes(batch)
        if len(states) != 4:
            raise ShapeError(f"RVTDetector states: expected 4 (h, c) pairs, got {len(states)}")
        checked = []
        for stage, (pair, (h_shape, c_shape)) in enumerate(zip(states, expected), start=1):
            if len(pair) != 2:
                raise ShapeError(f"RVTDetector states[{stage - 1}]: expected an (h, c) pair, got {len(pair)} items")
            h, c = pair
            if tuple(h.shape) != h_shape or tuple(c.shape) != c_shape:
                raise ShapeError(
                    f"RVTDetector state of stage {stage}: expected h, c {h_shape}, got {tuple(h.shape)}, "
                    f"{tuple(c.shape)}"
                )
            checked.append((h, c))
        return checked

    # ------------------------------------------------------------------ forward pieces
    def forward_backbone(
        self, x: torch.Tensor, states: Sequence[LstmState] | None = None
    ) -> tuple[dict[int, torch.Tensor], list[LstmState]]:
        """Run the recurrent backbone for one step.

        Args:
            x: float [B, 20, H, W] with (H, W) = ``config.in_res_hw`` (padded, see :func:`pad_to_input`).
            states: 4 × (h, c) float [B, C_s, H_s, W_s] from the previous step; ``None`` = zeros.

        Returns:
            (features, new_states): ``{1..4: [B, C_s, H_s, W_s]}`` and the 4 new (h, c) pairs.

        Raises:
            ShapeError: wrong input or state shapes.
        """
        self._check_input(x)
        batch = int(x.shape[0])
        if states is None:
            states = self.initial_states(batch, device=x.device, dtype=x.dtype)
        else:
            states = self._check_states(states, batch)
        return self.backbone(x, list(states))

    def forward_fpn(self, features: dict[int, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """PAFPN outputs (strides 8, 16, 32) from backbone features ``{2, 3, 4: ...}``."""
        return self.fpn(features)

    def forward_detect(self, features: dict[int, torch.Tensor]) -> torch.Tensor:
        """Decoded detections from backbone features.

        Args:
            features: the backbone features of :meth:`forward_backbone`.

        Returns:
            float [B, A, 5+nc]: (cx, cy, w, h) in input px, obj prob, class probs (car, pedestrian for Gen1).
        """
        return self.yolox_head(self.fpn(features))

    def forward_raw_head(self, features: dict[int, torch.Tensor]) -> torch.Tensor:
        """Pre-decode head logits [B, A, 5+nc] (t_x, t_y, t_w, t_h, obj logit, class logits) from backbone features."""
        return self.yolox_head.forward_raw(self.fpn(features))

    def forward(
        self, x: torch.Tensor, states: Sequence[LstmState] | None = None
    ) -> tuple[torch.Tensor, list[LstmState]]:
        """One recurrent step: backbone → FPN → decoded head.

        Args:
            x: float [B, 20, H, W], (H, W) = ``config.in_res_hw``.
            states: previous 4 × (h, c) or ``None`` (zeros).

        Returns:
            (decoded [B, A, 5+nc], new_states 4 × (h, c)).

        Raises:
            ShapeError: wrong input or state shapes.
        """
        features, new_states = self.forward_backbone(x, states)
        return self.forward_detect(features), new_states

    def step_flat(self, x: torch.Tensor, *flat_states: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """:meth:`forward` with flat states, the ONNX export signature.

        Args:
            x: float [B, 20, H, W].
            *flat_states: h1, c1, h2, c2, h3, c3, h4, c4.

        Returns:
            (decoded, h1, c1, ..., h4, c4) after this step.

        Raises:
            ShapeError: not exactly 8 state tensors, or wrong shapes.
        """
        if len(flat_states) != 8:
            raise ShapeError(f"step_flat: expected 8 state tensors (h1, c1, ..., h4, c4), got {len(flat_states)}")
        states = [(flat_states[2 * i], flat_states[2 * i + 1]) for i in range(4)]
        decoded, new_states = self.forward(x, states)
        flat_out: list[torch.Tensor] = []
        for h, c in new_states:
            flat_out.extend((h, c))
        return (decoded, *flat_out)

    def extra_repr(self) -> str:
        return f"config={self.config.name}: embed_dim={self.config.embed_dim}, in_res_hw={self.config.in_res_hw}"


__all__ = ["RVTDetector", "pad_to_input", "RVT_HW"]
