"""RVT building blocks in plain PyTorch: attention, partitioning, ConvLSTM, YOLOX convolutions.

Module and parameter names follow the official uzh-rpg/RVT code so that ``state_dict()`` keys equal the
released checkpoints' keys; the operation order follows it too, so outputs match the official model bit for
bit on the same machine. Only ONNX-exportable ops are used (reshape/permute partitioning, explicit attention
math, no ``nn.MultiheadAttention``).
"""

from __future__ import annotations

from davis_rig.models.rvt._torch import nn, torch

# ----------------------------------------------------------------------------- channels-last attention


class LayerScale(nn.Module):
    """Per-channel scale ``x * gamma`` (channels last); key ``gamma`` [C]."""

    def __init__(self, dim: int, init_value: float = 1e-5):
        super().__init__()
        self.gamma = nn.Parameter(init_value * torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class MLP(nn.Module):
    """Linear(C→rC) → exact GELU → Linear(rC→C), channels last; keys ``net.0.0`` and ``net.2``."""

    def __init__(self, dim: int, expansion_ratio: int = 4):
        super().__init__()
        inner_dim = int(dim * expansion_ratio)
        self.net = nn.Sequential(
            nn.Sequential(nn.Linear(dim, inner_dim, bias=True), nn.GELU()),
            nn.Identity(),  # dropout p=0 in the official model (index kept for the key layout)
            nn.Linear(inner_dim, dim, bias=True),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class SelfAttention(nn.Module):
    """Multi-head self-attention over the tokens of each partition, channels last.

    ``qkv`` is head-interleaved as in the official ``SelfAttentionCl``: output channel
    ``h * 3 * dim_head + s * dim_head + d`` for s ∈ (q, k, v). Logits are ``(q @ kᵀ) * dim_head**-0.5``.
    """

    def __init__(self, dim: int, dim_head: int):
        super().__init__()
        self.num_heads = dim // dim_head
        self.dim_head = dim_head
        self.scale = dim_head**-0.5
        self.qkv = nn.Linear(dim, dim * 3, bias=True)
        self.proj = nn.Linear(dim, dim, bias=True)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Attend within each partition.

        Args:
            x: float [P, ph, pw, C] (P partitions of ph×pw tokens).

        Returns:
            float [P, ph, pw, C].
        """
        partitions = x.shape[0]
        restore_shape = x.shape[:-1]
        qkv = self.qkv(x).view(partitions, -1, self.num_heads, self.dim_head * 3).transpose(1, 2)
        q, k, v = qkv.chunk(3, dim=3)
        attn = (q @ k.transpose(-2, -1)) * self.scale
        attn = attn.softmax(dim=-1)
        out = (attn @ v).transpose(1, 2).reshape(restore_shape + (-1,))
        return self.proj(out)


def window_partition(x: torch.Tensor, window_hw: tuple[int, int]) -> torch.Tensor:
    """Split [B, H, W, C] into non-overlapping windows [B·(H/ph)·(W/pw), ph, pw, C] (row-major)."""
    batch, height, width, channels = x.shape
    ph, pw = window_hw
    x = x.view(batch, height // ph, ph, width // pw, pw, channels)
    return x.permute(0, 1, 3, 2, 4, 5).contiguous().view(-1, ph, pw, channels)


def window_reverse(windows: torch.Tensor, window_hw: tuple[int, int], img_hw: tuple[int, int]) -> torch.Tensor:
    """Inverse of :func:`window_partition`: [B·n, ph, pw, C] → [B, H, W, C]."""
    height, width = img_hw
    ph, pw = window_hw
    channels = windows.shape[-1]
    x = windows.view(-1, height // ph, width // pw, ph, pw, channels)
    return x.permute(0, 1, 3, 2, 4, 5).contiguous().view(-1, height, width, channels)


def grid_partition(x: torch.Tensor, grid_hw: tuple[int, int]) -> torch.Tensor:
    """Split [B, H, W, C] into dilated grids [B·(H/gh)·(W/gw), gh, gw, C] (token stride H/gh, W/gw)."""
    batch, height, width, channels = x.shape
    gh, gw = grid_hw
    x = x.view(batch, gh, height // gh, gw, width // gw, channels)
    return x.permute(0, 2, 4, 1, 3, 5).contiguous().view(-1, gh, gw, channels)


def grid_reverse(windows: torch.Tensor, grid_hw: tuple[int, int], img_hw: tuple[int, int]) -> torch.Tensor:
    """Inverse of :func:`grid_partition`: [B·n, gh, gw, C] → [B, H, W, C]."""
    height, width = img_hw
    gh, gw = grid_hw
    channels = windows.shape[-1]
    x = windows.view(-1, height // gh, width // gw, gh, gw, channels)
    return x.permute(0, 3, 1, 4, 2, 5).contiguous().view(-1, height, width, channels)


class PartitionAttention(nn.Module):
    """Pre-norm transformer block on window or grid partitions, channels last (official ``PartitionAttentionCl``).

    ``x ← x + γ1 ⊙ Attn(partition(Norm1(x)))``, ``x ← x + γ2 ⊙ MLP(Norm2(x))``. ``norm1`` is ``Identity``
    (no key) when ``skip_first_norm`` (first window block after the normalising downsample).
    """

    def __init__(
        self,
        dim: int,
        *,
        grid: bool,
        partition_hw: tuple[int, int],
        dim_head: int,
        mlp_ratio: int = 4,
        ls_init_value: float = 1e-5,
        skip_first_norm: bool = False,
    ):
        super().__init__()
        self.grid = grid
        self.partition_hw = tuple(partition_hw)
        self.norm1 = nn.Identity() if skip_first_norm else nn.LayerNorm(dim, eps=1e-5)
        self.self_attn = SelfAttention(dim, dim_head=dim_head)
        self.ls1 = LayerScale(dim, ls_init_value)
        self.norm2 = nn.LayerNorm(dim, eps=1e-5)
        self.mlp = MLP(dim, expansion_ratio=mlp_ratio)
        self.ls2 = LayerScale(dim, ls_init_value)

    def _partition_attn(self, x: torch.Tensor) -> torch.Tensor:
        img_hw = (x.shape[1], x.shape[2])
        if self.grid:
            return grid_reverse(self.self_attn(grid_partition(x, self.partition_hw)), self.partition_hw, img_hw)
        return window_reverse(self.self_attn(window_partition(x, self.partition_hw)), self.partition_hw, img_hw)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Args: x float [B, H, W, C]. Returns: float [B, H, W, C]."""
        x = x + self.ls1(self._partition_attn(self.norm1(x)))
        x = x + self.ls2(self.mlp(self.norm2(x)))
        return x


class AttentionPair(nn.Module):
    """Window block then grid block (official ``MaxVitAttentionPairCl``): keys ``att_window``, ``att_grid``."""

    def __init__(
        self,
        dim: int,
        *,
        skip_first_norm: bool,
        partition_hw: tuple[int, int],
        dim_head: int,
        mlp_ratio: int,
        ls_init_value: float,
    ):
        super().__init__()
        common = {
            "partition_hw": partition_hw,
            "dim_head": dim_head,
            "mlp_ratio": mlp_ratio,
            "ls_init_value": ls_init_value,
        }
        self.att_window = PartitionAttention(dim, grid=False, skip_first_norm=skip_first_norm, **common)
        self.att_grid = PartitionAttention(dim, grid=True, skip_first_norm=False, **common)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.att_grid(self.att_window(x))


class ConvDownsample(nn.Module):
    """Overlapping strided conv (no bias) NCHW → NHWC → LayerNorm (official ``ConvDownsampling_Cf2Cl``).

    Kernel ``2·(factor−1)+1``, padding ``kernel // 2``, stride ``factor``; keys ``conv.weight``, ``norm.*``.
    """

    def __init__(self, dim_in: int, dim_out: int, factor: int):
        super().__init__()
        kernel = (factor - 1) * 2 + 1
        self.conv = nn.Conv2d(dim_in, dim_out, kernel_size=kernel, padding=kernel // 2, stride=factor, bias=False)
        self.norm = nn.LayerNorm(dim_out, eps=1e-5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """Args: x float [B, C_in, H, W]. Returns: float [B, H/f, W/f, C_out] (channels last)."""
        return self.norm(self.conv(x).permute(0, 2, 3, 1))


class ConvLSTM(nn.Module):
    """1×1-convolution LSTM cell, NCHW (official ``DWSConvLSTM2d`` with ``dws_conv=False``).

    ``z = conv1x1(cat[x, h])``; ``f, i, o = sigmoid(z[:3C])`` (in this order), ``g = tanh(z[3C:])``;
    ``c' = f·c + i·g``; ``h' = o·tanh(c')``. Key ``conv1x1.{weight,bias}``.
    """

    def __init__(self, dim: int):
        super().__init__()
        self.dim = dim
        self.conv1x1 = nn.Conv2d(dim * 2, dim * 4, kernel_size=1)

    def forward(self, x: torch.Tensor, h_prev: torch.Tensor, c_prev: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """One step.

        Args:
            x: float [B, C, H, W]; h_prev, c_prev: float [B, C, H, W] (zeros for the first step).

        Returns:
            (h, c): float [B, C, H, W] each.
        """
        mix = self.conv1x1(torch.cat((x, h_prev), dim=1))
        # torch.split (not tensor_split, the same slices) exports as one ONNX Split instead of a Loop per call
        gates, cell_input = torch.split(mix, [self.dim * 3, self.dim], dim=1)
        gates = torch.sigmoid(gates)
        forget_gate, input_gate, output_gate = torch.split(gates, self.dim, dim=1)
        cell_input = torch.tanh(cell_input)
        c = forget_gate * c_prev + input_gate * cell_input
        h = output_gate * torch.tanh(c)
        return h, c


# ----------------------------------------------------------------------------- YOLOX convolutions (NCHW)


class BaseConv(nn.Module):
    """Conv2d(k, stride, pad (k−1)//2, no bias) → BatchNorm2d(eps 1e-5) → SiLU; keys ``conv``, ``bn``."""

    def __init__(self, in_channels: int, out_channels: int, ksize: int, stride: int = 1):
        super().__init__()
        self.conv = nn.Conv2d(
            in_channels, out_channels, kernel_size=ksize, stride=stride, padding=(ksize - 1) // 2, bias=False
        )
        self.bn = nn.BatchNorm2d(out_channels)
        self.act = nn.SiLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(self.bn(self.conv(x)))


class Bottleneck(nn.Module):
    """BaseConv1×1 → BaseConv3×3, no residual (the PAFPN passes ``shortcut=False``)."""

    def __init__(self, channels: int):
        super().__init__()
        self.conv1 = BaseConv(channels, channels, 1)
        self.conv2 = BaseConv(channels, channels, 3)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv2(self.conv1(x))


class CSPLayer(nn.Module):
    """YOLOX CSP layer: conv3(cat[m(conv1(x)), conv2(x)]), hidden = out/2, ``n`` bottlenecks in ``m``."""

    def __init__(self, in_channels: int, out_channels: int, n: int):
        super().__init__()
        hidden = int(out_channels * 0.5)
        self.conv1 = BaseConv(in_channels, hidden, 1)
        self.conv2 = BaseConv(in_channels, hidden, 1)
        self.conv3 = BaseConv(2 * hidden, out_channels, 1)
        self.m = nn.Sequential(*[Bottleneck(hidden) for _ in range(n)])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x_1 = self.conv1(x)
        x_2 = self.conv2(x)
        x_1 = self.m(x_1)
        return self.conv3(torch.cat((x_1, x_2), dim=1))
