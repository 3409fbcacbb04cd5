"""Import torch for the RVT modules, or fail with a message naming the missing extra."""

from __future__ import annotations

from davis_rig.errors import MissingDependencyError

try:
    import torch
    import torch.nn.functional as F
    from torch import nn
except ImportError as exc:  # pragma: no cover - exercised only without torch
    raise MissingDependencyError(
        "the RVT PyTorch model needs torch: pip install 'davis_rig[torch]' (CPU wheel: pip install torch==2.13.0)"
    ) from exc

__all__ = ["torch", "nn", "F"]
