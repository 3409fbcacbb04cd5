"""Import torch for the RVT modules, or fail with a message naming the missing extra."""

from __future__ import annotations

from davis_rig._lazy import optional_dependency

with optional_dependency("the RVT PyTorch model"):
    import torch
    import torch.nn.functional as F
    from torch import nn

__all__ = ["torch", "nn", "F"]
