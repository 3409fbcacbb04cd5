"""RVT (Recurrent Vision Transformer) detector configuration: Gen1 presets and official-config parsing.

Pure Python (no torch): the ONNX runner and the tools can read a config without the torch extra.

The supported architecture is the one of the released Gen1 models (uzh-rpg/RVT, MaxViT-RNN backbone +
YOLOX PAFPN + YOLOX head): overlapping patch downsampling, window + grid attention blocks without relative
position bias, exact-GELU MLP, 1×1 ConvLSTM, PAFPN without residual bottlenecks.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from typing import Any, Final, Mapping

from davis_rig.errors import FormatError
from davis_rig.types import RVT_HW

#: Spatial stride of each backbone stage relative to the network input, px.
STAGE_STRIDES = (4, 8, 16, 32)
#: Backbone stages fed to the FPN (1-based, as in the official ``fpn.in_stages``).
FPN_IN_STAGES = (2, 3, 4)


def padded_input_hw(dataset_hw: tuple[int, int] = RVT_HW, partition_split_32: int = 1) -> tuple[int, int]:
    """Round a sensor size up to the network input size, as the official ``config/modifier.py`` does.

    Args:
        dataset_hw: sensor (height, width), px; default the Gen1 frame (240, 304).
        partition_split_32: the backbone's ``partition_split_32`` (1, 2 or 4).

    Returns:
        (height, width), px: each rounded up to a multiple of ``32 * partition_split_32``.
    """
    multiple = 32 * partition_split_32
    return tuple(int(math.ceil(size / multiple) * multiple) for size in dataset_hw)


#: The released Gen1 models' input, (height, width) px: the 240x304 frame zero-padded to (256, 320).
GEN1_INPUT_HW: Final = padded_input_hw(RVT_HW)


@dataclass(frozen=True)
class RVTConfig:
    """Hyper-parameters of one RVT detector (no parameter depends on ``in_res_hw``).

    Attributes:
        embed_dim: channels of stage 1 (C); stage dims are ``C * dim_multiplier``.
        dim_head: channels per attention head (heads per stage = stage dim / dim_head).
        num_blocks: (window, grid) attention pairs per stage, 4 entries.
        dim_multiplier: channel multiplier per stage, 4 entries.
        fpn_depth: PAFPN depth; bottlenecks per CSP layer = ``round(3 * fpn_depth)``.
        input_channels: input histogram channels (2 polarities × 10 time bins).
        num_classes: detector classes (Gen1: 0 = car, 1 = pedestrian).
        in_res_hw: padded network input (height, width), px; multiples of ``32 * partition_split_32``.
        partition_split_32: the official ``partition_split_32`` (attention partition = in_res / (32 · split)).
        mlp_ratio: hidden/input width of the attention MLPs.
        ls_init_value: LayerScale initial value (only matters for freshly built models).
        stem_patch_size: downsampling factor of stage 1 (official ``stem.patch_size``).
        name: a label for reports (e.g. ``"RVT-T"``); not part of the architecture.
    """

    embed_dim: int
    dim_head: int
    num_blocks: tuple[int, ...] = (1, 1, 1, 1)
    dim_multiplier: tuple[int, ...] = (1, 2, 4, 8)
    fpn_depth: float = 0.33
    input_channels: int = 20
    num_classes: int = 2
    in_res_hw: tuple[int, int] = GEN1_INPUT_HW
    partition_split_32: int = 1
    mlp_ratio: int = 4
    ls_init_value: float = 1e-5
    stem_patch_size: int = 4
    name: str = field(default="custom", compare=False)

    def __post_init__(self):
        object.__setattr__(self, "num_blocks", tuple(int(v) for v in self.num_blocks))
        object.__setattr__(self, "dim_multiplier", tuple(int(v) for v in self.dim_multiplier))
        object.__setattr__(self, "in_res_hw", tuple(int(v) for v in self.in_res_hw))
        problems = []
        if len(self.num_blocks) != 4 or min(self.num_blocks) < 1:
            problems.append(f"num_blocks: expected 4 positive ints, got {self.num_blocks}")
        if len(self.dim_multiplier) != 4 or min(self.dim_multiplier) < 1:
            problems.append(f"dim_multiplier: expected 4 positive ints, got {self.dim_multiplier}")
        if self.embed_dim < 1 or self.dim_head < 1:
            problems.append(f"embed_dim/dim_head: expected positive, got {self.embed_dim}/{self.dim_head}")
        elif not problems:
            for dim in self.stage_dims:
                if dim % self.dim_head:
                    problems.append(f"stage dim {dim} is not a multiple of dim_head {self.dim_head}")
        if self.partition_split_32 not in (1, 2, 4):
            problems.append(f"partition_split_32: expected 1, 2 or 4, got {self.partition_split_32}")
        multiple = 32 * self.partition_split_32
        if len(self.in_res_hw) != 2 or any(v <= 0 or v % multiple for v in self.in_res_hw):
            problems.append(f"in_res_hw: expected 2 positive multiples of {multiple}, got {self.in_res_hw}")
        if self.stem_patch_size not in (2, 4, 8):
            problems.append(f"stem_patch_size: expected 2, 4 or 8, got {self.stem_patch_size}")
        if not problems:
            partition = self.partition_size
            for stage in range(1, 5):
                stage_hw = self.stage_hw(stage)
                stride = self.stage_strides[stage - 1]
                if any(v % stride for v in self.in_res_hw) or any(
                    size % part for size, part in zip(stage_hw, partition)
                ):
                    problems.append(
                        f"stage {stage} map {stage_hw} (stride {stride}) is not divisible by the attention "
                        f"partition {partition} (from in_res_hw {self.in_res_hw})"
                    )
                    break
        if self.fpn_depth <= 0 or self.input_channels < 1 or self.num_classes < 1 or self.mlp_ratio < 1:
            problems.append("fpn_depth, input_channels, num_classes and mlp_ratio must be positive")
        if problems:
            raise FormatError("invalid RVTConfig: " + "; ".join(problems))

    # ------------------------------------------------------------------ presets
    @classmethod
    def tiny(cls, **overrides) -> "RVTConfig":
        """RVT-T Gen1 (4,405,141 parameters): C=32, dim_head 32, FPN depth 0.33."""
        return cls(**{"embed_dim": 32, "dim_head": 32, "fpn_depth": 0.33, "name": "RVT-T", **overrides})

    @classmethod
    def small(cls, **overrides) -> "RVTConfig":
        """RVT-S Gen1 (9,870,165 parameters): C=48, dim_head 24, FPN depth 0.33."""
        return cls(**{"embed_dim": 48, "dim_head": 24, "fpn_depth": 0.33, "name": "RVT-S", **overrides})

    @classmethod
    def base(cls, **overrides) -> "RVTConfig":
        """RVT-B Gen1 (18,536,469 parameters): C=64, dim_head 32, FPN depth 0.67."""
        return cls(**{"embed_dim": 64, "dim_head": 32, "fpn_depth": 0.67, "name": "RVT-B", **overrides})

    @classmethod
    def mini(cls, **overrides) -> "RVTConfig":
        """The reduced test config of ``rvt_mini_fixture`` (80,765 parameters): C=8, dims 8/8/16/32."""
        return cls(
            **{
                "embed_dim": 8,
                "dim_head": 8,
                "dim_multiplier": (1, 1, 2, 4),
                "fpn_depth": 0.33,
                "name": "RVT-mini",
                **overrides,
            }
        )

    @classmethod
    def nano(cls, **overrides) -> "RVTConfig":
        """RVT-T at half width for CPU training (1,115,093 parameters): C=16, dim_head 16, FPN depth 0.33."""
        return cls(**{"embed_dim": 16, "dim_head": 16, "fpn_depth": 0.33, "name": "RVT-nano", **overrides})

    @classmethod
    def presets(cls) -> dict[str, "RVTConfig"]:
        """All named presets: ``{"tiny": ..., "small": ..., "base": ..., "mini": ..., "nano": ...}``."""
        return {"tiny": cls.tiny(), "small": cls.small(), "base": cls.base(), "mini": cls.mini(), "nano": cls.nano()}

    # ------------------------------------------------------------------ derived
    @property
    def stage_dims(self) -> tuple[int, int, int, int]:
        """Channels of the 4 backbone stages."""
        return tuple(self.embed_dim * m for m in self.dim_multiplier)

    @property
    def num_heads(self) -> tuple[int, int, int, int]:
        """Attention heads per stage."""
        return tuple(dim // self.dim_head for dim in self.stage_dims)

    @property
    def stage_strides(self) -> tuple[int, int, int, int]:
        """Stride of each stage's feature map relative to the input, px."""
        first = self.stem_patch_size
        return (first, first * 2, first * 4, first * 8)

    @property
    def partition_size(self) -> tuple[int, int]:
        """Window/grid partition (height, width) in tokens: ``in_res_hw // (32 * partition_split_32)``."""
        return tuple(v // (32 * self.partition_split_32) for v in self.in_res_hw)

    @property
    def fpn_in_channels(self) -> tuple[int, int, int]:
        """Channels of the FPN inputs / outputs (backbone stages 2, 3, 4)."""
        return tuple(self.stage_dims[s - 1] for s in FPN_IN_STAGES)

    @property
    def fpn_num_bottlenecks(self) -> int:
        """Bottlenecks per CSP layer, ``round(3 * fpn_depth)``."""
        return int(round(3 * self.fpn_depth))

    @property
    def head_strides(self) -> tuple[int, int, int]:
        """Strides of the 3 head levels, px."""
        return tuple(self.stage_strides[s - 1] for s in FPN_IN_STAGES)

    @property
    def head_hidden_dim(self) -> int:
        """YOLOX head width: ``int(256 * c_last / 1024)``."""
        return int(256 * (self.fpn_in_channels[-1] / 1024))

    @property
    def num_anchors(self) -> int:
        """Anchors (one per cell of the 3 head levels); 1680 at 256×320."""
        height, width = self.in_res_hw
        return sum((height // s) * (width // s) for s in self.head_strides)

    @property
    def num_outputs(self) -> int:
        """Values per anchor in the decoded output: cx, cy, w, h, obj, one per class."""
        return 5 + self.num_classes

    def stage_hw(self, stage: int) -> tuple[int, int]:
        """Feature map (height, width) of backbone stage ``stage`` (1..4) for ``in_res_hw``."""
        stride = self.stage_strides[stage - 1]
        return (self.in_res_hw[0] // stride, self.in_res_hw[1] // stride)

    def state_shapes(self, batch: int = 1) -> list[tuple[tuple[int, int, int, int], tuple[int, int, int, int]]]:
        """Shapes of the recurrent states: 4 × (h shape, c shape), each [B, C_s, H_s, W_s]."""
        shapes = []
        for stage in range(1, 5):
            shape = (int(batch), self.stage_dims[stage - 1], *self.stage_hw(stage))
            shapes.append((shape, shape))
        return shapes

    @property
    def flat_state_names(self) -> tuple[str, ...]:
        """Names of the flat recurrent-state tensors: ``("h1", "c1", ..., "h4", "c4")``."""
        return tuple(f"{kind}{stage}" for stage in range(1, 5) for kind in ("h", "c"))

    # ------------------------------------------------------------------ (de)serialisation
    def to_dict(self) -> dict[str, Any]:
        """Flat JSON-able dict of the fields (``RVTConfig.from_dict`` reads it back)."""
        out = asdict(self)
        out["format"] = "davis_rig-rvt-config/1"
        for key in ("num_blocks", "dim_multiplier", "in_res_hw"):
            out[key] = list(out[key])
        return out

    def to_json(self) -> str:
        """``to_dict()`` as a compact JSON string (stored in safetensors / ONNX metadata)."""
        return json.dumps(self.to_dict(), sort_keys=True)

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | str) -> "RVTConfig":
        """Build a config from a flat dict (``to_dict``), an official hydra model config, or a fixture config.

        Accepted forms: the flat field dict of :meth:`to_dict`; the official resolved ``model`` config
        (``{"backbone": {"embed_dim", "stage": {"attention": {"dim_head", ...}}, ...}, "fpn": {"depth"},
        "head": {"num_classes"}}``), optionally wrapped as ``{"model": ...}``; the nested
        ``rvt-fixture-config/1`` JSON stored in the fixtures' metadata key ``config``. A JSON string is parsed.

        Args:
            d: the mapping, or its JSON text.

        Returns:
            The config.

        Raises:
            FormatError: not valid JSON, missing required entries, or an architecture option this
                implementation does not support (e.g. ``use_torch_mha``, gated MLP, depthwise LSTM conv).
        """
        if isinstance(d, (str, bytes)):
            try:
                d = json.loads(d)
            except json.JSONDecodeError as exc:
                raise FormatError(f"RVT config is not valid JSON: {exc}") from exc
        if not isinstance(d, Mapping):
            raise FormatError(f"RVT config: expected a mapping, got {type(d).__name__}")
        if "model" in d and isinstance(d["model"], Mapping) and "backbone" in d["model"]:
            d = d["model"]
        if "backbone" in d and isinstance(d["backbone"], Mapping):
            return cls(**_from_nested(d)).with_preset_name()
        names = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - names - {"format"})
        if unknown:
            raise FormatError(f"RVT config: unknown keys {unknown}; expected a subset of {sorted(names)}")
        missing = [name for name in ("embed_dim", "dim_head") if name not in d]
        if missing:
            raise FormatError(f"RVT config: missing required keys {missing}")
        config = cls(**{k: v for k, v in d.items() if k in names})
        return config if "name" in d else config.with_preset_name()

    def with_preset_name(self) -> "RVTConfig":
        """This config, named after the preset it equals (``"RVT-T"``, ...), or unchanged if none."""
        for preset in RVTConfig.presets().values():
            if preset == self:
                return replace(self, name=preset.name)
        return self


def _get(mapping: Mapping[str, Any], *path: str, default: Any = None) -> Any:
    node: Any = mapping
    for key in path:
        if not isinstance(node, Mapping) or key not in node:
            return default
        node = node[key]
    return node


def _from_nested(d: Mapping[str, Any]) -> dict[str, Any]:
    """Map an official hydra model config or an ``rvt-fixture-config/1`` dict onto RVTConfig fields."""
    backbone = d["backbone"]
    # hydra: backbone.stage.attention / .lstm / .downsample; fixture JSON: backbone.attention / .lstm / .downsample
    attention = _get(backbone, "stage", "attention") or _get(backbone, "attention") or {}
    lstm = _get(backbone, "stage", "lstm") or _get(backbone, "lstm") or {}
    downsample = _get(backbone, "stage", "downsample") or _get(backbone, "downsample") or {}

    unsupported = []
    for label, value, wanted in (
        ("attention.use_torch_mha", attention.get("use_torch_mha", False), False),
        ("attention.mlp_gated", attention.get("mlp_gated", False), False),
        ("attention.mlp_bias", attention.get("mlp_bias", True), True),
        ("attention.attention_bias", attention.get("attention_bias", True), True),
        ("attention.mlp_activation", attention.get("mlp_activation", "gelu"), "gelu"),
        ("lstm.dws_conv", lstm.get("dws_conv", False), False),
        ("downsample.type", downsample.get("type", "patch"), "patch"),
        ("downsample.overlap", downsample.get("overlap", True), True),
        ("downsample.norm_affine", downsample.get("norm_affine", True), True),
        ("backbone.enable_masking", backbone.get("enable_masking", False), False),
        ("fpn.depthwise", _get(d, "fpn", "depthwise", default=False), False),
        ("fpn.act", _get(d, "fpn", "act", default="silu"), "silu"),
        ("head.act", _get(d, "head", "act", default="silu"), "silu"),
        ("head.depthwise", _get(d, "head", "depthwise", default=False), False),
    ):
        if value != wanted:
            unsupported.append(f"{label}={value!r} (supported: {wanted!r})")
    in_stages = _get(d, "fpn", "in_stages", default=list(FPN_IN_STAGES))
    if tuple(in_stages) != FPN_IN_STAGES:
        unsupported.append(f"fpn.in_stages={list(in_stages)} (supported: {list(FPN_IN_STAGES)})")
    if unsupported:
        raise FormatError("RVT config uses options this implementation does not support: " + "; ".join(unsupported))

    embed_dim = backbone.get("embed_dim")
    dim_head = attention.get("dim_head", 32)
    if embed_dim is None:
        raise FormatError("RVT config: backbone.embed_dim is missing")
    num_classes = _get(d, "head", "num_classes", default=None)
    if num_classes is None:
        num_classes = d.get("num_classes", 2)
    in_res_hw = backbone.get("in_res_hw") or d.get("in_res_hw") or GEN1_INPUT_HW
    stem_patch = _get(backbone, "stem", "patch_size", default=None) or backbone.get("stem_patch_size", 4)
    fpn_depth = _get(d, "fpn", "depth", default=None)
    if fpn_depth is None:
        raise FormatError("RVT config: fpn.depth is missing")
    out = {
        "embed_dim": int(embed_dim),
        "dim_head": int(dim_head),
        "num_blocks": tuple(backbone.get("num_blocks", (1, 1, 1, 1))),
        "dim_multiplier": tuple(backbone.get("dim_multiplier", (1, 2, 4, 8))),
        "fpn_depth": float(fpn_depth),
        "input_channels": int(backbone.get("input_channels", 20)),
        "num_classes": int(num_classes),
        "in_res_hw": tuple(in_res_hw),
        "partition_split_32": int(backbone.get("partition_split_32", 1)),
        "mlp_ratio": int(attention.get("mlp_ratio", 4)),
        "ls_init_value": float(attention.get("ls_init_value", 1e-5)),
        "stem_patch_size": int(stem_patch),
    }
    partition = attention.get("partition_size") or backbone.get("partition_size")
    if partition is not None:
        expected = tuple(v // (32 * out["partition_split_32"]) for v in out["in_res_hw"])
        if tuple(partition) != expected:
            raise FormatError(
                f"RVT config: partition_size {list(partition)} does not follow in_res_hw {list(out['in_res_hw'])} "
                f"and partition_split_32 {out['partition_split_32']} (expected {list(expected)})"
            )
    return out
