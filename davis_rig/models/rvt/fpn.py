"""YOLOX PAFPN neck as configured in RVT (no residual bottlenecks, nearest ×2 upsampling)."""

from __future__ import annotations

from davis_rig.models.rvt._torch import F, nn, torch
from davis_rig.models.rvt.config import FPN_IN_STAGES
from davis_rig.models.rvt.layers import BaseConv, CSPLayer


def _upsample2(x: torch.Tensor) -> torch.Tensor:
    # The official code uses mode="nearest-exact"; for an integer ×2 factor it picks the same source pixel
    # (floor((i + 0.5) / 2) == floor(i / 2)), so "nearest" is identical and also exports to ONNX (Resize).
    return F.interpolate(x, scale_factor=2.0, mode="nearest")


class PAFPN(nn.Module):
    """Top-down then bottom-up feature pyramid over backbone stages 2, 3, 4 (official ``YOLOPAFPN``).

    Keys: ``lateral_conv0``, ``C3_p4``, ``reduce_conv1``, ``C3_p3``, ``bu_conv2``, ``C3_n3``, ``bu_conv1``, ``C3_n4``.
    """

    def __init__(self, in_channels: tuple[int, int, int], num_bottlenecks: int):
        super().__init__()
        c0, c1, c2 = in_channels
        n = num_bottlenecks
        self.lateral_conv0 = BaseConv(c2, c1, 1, 1)
        self.C3_p4 = CSPLayer(2 * c1, c1, n)
        self.reduce_conv1 = BaseConv(c1, c0, 1, 1)
        self.C3_p3 = CSPLayer(2 * c0, c0, n)
        self.bu_conv2 = BaseConv(c0, c0, 3, 2)
        self.C3_n3 = CSPLayer(2 * c0, c1, n)
        self.bu_conv1 = BaseConv(c1, c1, 3, 2)
        self.C3_n4 = CSPLayer(2 * c1, c2, n)

    def forward(self, features: dict[int, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Fuse the backbone features.

        Args:
            features: ``{2: x2 [B, c0, H/8, W/8], 3: x1 [B, c1, H/16, W/16], 4: x0 [B, c2, H/32, W/32]}``
                (other keys ignored), float.

        Returns:
            (out_s8 [B, c0, H/8, W/8], out_s16 [B, c1, H/16, W/16], out_s32 [B, c2, H/32, W/32]), float.
        """
        x2, x1, x0 = (features[stage] for stage in FPN_IN_STAGES)

        fpn_out0 = self.lateral_conv0(x0)
        f_out0 = self.C3_p4(torch.cat([_upsample2(fpn_out0), x1], 1))

        fpn_out1 = self.reduce_conv1(f_out0)
        pan_out2 = self.C3_p3(torch.cat([_upsample2(fpn_out1), x2], 1))

        pan_out1 = self.C3_n3(torch.cat([self.bu_conv2(pan_out2), fpn_out1], 1))
        pan_out0 = self.C3_n4(torch.cat([self.bu_conv1(pan_out1), fpn_out0], 1))
        return pan_out2, pan_out1, pan_out0
