"""YOLOX detection head (official ``YOLOXHead``, inference path) with explicit raw/decoded outputs."""

from __future__ import annotations

from davis_rig.models.rvt._torch import nn, torch
from davis_rig.models.rvt.layers import BaseConv


class YOLOXHead(nn.Module):
    """Decoupled YOLOX head over 3 levels (keys ``stems``, ``cls_convs``, ``reg_convs``, ``*_preds``).

    Per level k: ``stem`` (1×1) → cls branch (2× 3×3) → ``cls_preds``; reg branch (2× 3×3) → ``reg_preds`` and
    ``obj_preds``. No buffers: the decode grids are computed from the feature sizes on every call (so no
    inference-mode tensor is ever cached, and ONNX export folds them into constants).
    """

    def __init__(self, num_classes: int, strides: tuple[int, ...], in_channels: tuple[int, ...]):
        super().__init__()
        self.num_classes = num_classes
        self.strides = tuple(strides)
        hidden = int(256 * (in_channels[-1] / 1024))
        self.cls_convs = nn.ModuleList(
            nn.Sequential(BaseConv(hidden, hidden, 3, 1), BaseConv(hidden, hidden, 3, 1)) for _ in in_channels
        )
        self.reg_convs = nn.ModuleList(
            nn.Sequential(BaseConv(hidden, hidden, 3, 1), BaseConv(hidden, hidden, 3, 1)) for _ in in_channels
        )
        self.cls_preds = nn.ModuleList(nn.Conv2d(hidden, num_classes, 1, 1, 0) for _ in in_channels)
        self.reg_preds = nn.ModuleList(nn.Conv2d(hidden, 4, 1, 1, 0) for _ in in_channels)
        self.obj_preds = nn.ModuleList(nn.Conv2d(hidden, 1, 1, 1, 0) for _ in in_channels)
        # registered last, like the official head, so that state_dict() lists keys in the official order
        self.stems = nn.ModuleList(BaseConv(c, hidden, 1, 1) for c in in_channels)

    def _level_outputs(self, fpn_features) -> list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]:
        outputs = []
        for k, x in enumerate(fpn_features):
            x = self.stems[k](x)
            cls_output = self.cls_preds[k](self.cls_convs[k](x))
            reg_feat = self.reg_convs[k](x)
            outputs.append((self.reg_preds[k](reg_feat), self.obj_preds[k](reg_feat), cls_output))
        return outputs

    @staticmethod
    def _flatten(level_maps: list[torch.Tensor]) -> torch.Tensor:
        # [B, 5+nc, H_k, W_k] per level -> [B, A, 5+nc], levels in stride order, cells row-major
        return torch.cat([m.flatten(start_dim=2) for m in level_maps], dim=2).permute(0, 2, 1)

    def forward_raw(self, fpn_features) -> torch.Tensor:
        """Pre-decode, pre-sigmoid outputs.

        Args:
            fpn_features: 3 float maps [B, c_k, H/s_k, W/s_k] (strides 8, 16, 32).

        Returns:
            float [B, A, 5+nc]: (t_x, t_y, t_w, t_h, obj logit, class logits...).
        """
        return self._flatten([torch.cat([r, o, c], 1) for r, o, c in self._level_outputs(fpn_features)])

    def decode_grids(self, fpn_features, dtype, device) -> tuple[torch.Tensor, torch.Tensor]:
        """Anchor cell (column, row) [1, A, 2] and stride [1, A, 1] tensors for these feature sizes."""
        grids, strides = [], []
        for x, stride in zip(fpn_features, self.strides):
            height, width = int(x.shape[-2]), int(x.shape[-1])
            yv, xv = torch.meshgrid(
                torch.arange(height, device=device, dtype=dtype),
                torch.arange(width, device=device, dtype=dtype),
                indexing="ij",
            )
            grid = torch.stack((xv, yv), 2).view(1, -1, 2)
            grids.append(grid)
            strides.append(torch.full((1, grid.shape[1], 1), stride, device=device, dtype=dtype))
        return torch.cat(grids, dim=1), torch.cat(strides, dim=1)

    def forward(self, fpn_features) -> torch.Tensor:
        """Decoded detections (official inference output, no +0.5 cell offset).

        Args:
            fpn_features: 3 float maps [B, c_k, H/s_k, W/s_k] (strides 8, 16, 32).

        Returns:
            float [B, A, 5+nc]: (cx, cy, w, h) in input px, sigmoid(obj), sigmoid(class_i)...
        """
        outputs = self._flatten(
            [torch.cat([r, o.sigmoid(), c.sigmoid()], 1) for r, o, c in self._level_outputs(fpn_features)]
        )
        grids, strides = self.decode_grids(fpn_features, outputs.dtype, outputs.device)
        return torch.cat(
            [
                (outputs[..., 0:2] + grids) * strides,
                torch.exp(outputs[..., 2:4]) * strides,
                outputs[..., 4:],
            ],
            dim=-1,
        )
