"""RVT recurrent MaxViT backbone: 4 stages of downsample → window/grid attention → ConvLSTM."""

from __future__ import annotations

from davis_rig.models.rvt._torch import nn, torch
from davis_rig.models.rvt.config import RVTConfig
from davis_rig.models.rvt.layers import AttentionPair, ConvDownsample, ConvLSTM

#: Recurrent state of one stage: (h, c), float [B, C_s, H_s, W_s] each.
LstmState = tuple[torch.Tensor, torch.Tensor]


class RVTStage(nn.Module):
    """One backbone stage (official ``RNNDetectorStage``); keys ``downsample_cf2cl``, ``att_blocks``, ``lstm``."""

    def __init__(self, dim_in: int, dim: int, downsample_factor: int, num_blocks: int, config: RVTConfig):
        super().__init__()
        self.downsample_cf2cl = ConvDownsample(dim_in, dim, downsample_factor)
        self.att_blocks = nn.ModuleList(
            AttentionPair(
                dim,
                skip_first_norm=(i == 0),  # the downsample output is already LayerNorm'ed
                partition_hw=config.partition_size,
                dim_head=config.dim_head,
                mlp_ratio=config.mlp_ratio,
                ls_init_value=config.ls_init_value,
            )
            for i in range(num_blocks)
        )
        self.lstm = ConvLSTM(dim)

    def forward(self, x: torch.Tensor, h_prev: torch.Tensor, c_prev: torch.Tensor) -> LstmState:
        """One step of the stage.

        Args:
            x: float [B, C_in, H, W].
            h_prev, c_prev: float [B, C, H/f, W/f], the stage's previous LSTM state.

        Returns:
            (h, c): float [B, C, H/f, W/f]; h is also the stage's feature map.
        """
        x = self.downsample_cf2cl(x)  # NCHW -> NHWC
        for block in self.att_blocks:
            x = block(x)
        x = x.permute(0, 3, 1, 2)  # NHWC -> NCHW
        return self.lstm(x, h_prev, c_prev)


class RVTBackbone(nn.Module):
    """The 4-stage recurrent backbone (official ``RNNDetector``); key ``stages.{0..3}``.

    States are explicit: ``forward`` takes and returns the list of 4 ``(h, c)`` tuples.
    """

    def __init__(self, config: RVTConfig):
        super().__init__()
        self.config = config
        dims = config.stage_dims
        dims_in = (config.input_channels,) + dims[:3]
        factors = (config.stem_patch_size, 2, 2, 2)
        self.stages = nn.ModuleList(
            RVTStage(dims_in[s], dims[s], factors[s], config.num_blocks[s], config) for s in range(4)
        )

    def forward(
        self, x: torch.Tensor, states: list[LstmState]
    ) -> tuple[dict[int, torch.Tensor], list[LstmState]]:
        """One recurrent step.

        Args:
            x: float [B, C_in, H, W], the padded input histogram.
            states: 4 × (h, c), float [B, C_s, H_s, W_s] (zeros at the start of a sequence).

        Returns:
            (features, new_states): features ``{1: h1, .., 4: h4}`` float [B, C_s, H/stride_s, W/stride_s];
            new_states 4 × (h, c).
        """
        features: dict[int, torch.Tensor] = {}
        new_states: list[LstmState] = []
        for index, stage in enumerate(self.stages):
            h, c = stage(x, states[index][0], states[index][1])
            new_states.append((h, c))
            features[index + 1] = h
            x = h
        return features, new_states
