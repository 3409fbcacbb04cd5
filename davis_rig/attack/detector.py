"""The frozen detector the attack optimises against: an RVT checkpoint in eval mode without parameter gradients."""

from __future__ import annotations

from pathlib import Path

from davis_rig.errors import CheckpointError

__all__ = ["detector_fingerprint", "load_attack_detector"]


def load_attack_detector(path=None, device=None):
    """The frozen detector of the attack: a torch checkpoint, eval mode, no parameter gradients.

    Args:
        path: ``.ckpt``/``.pt``/``.pth``/``.safetensors`` (official RVT checkpoints included); ``None`` = the
            bundled default detector's weights (:func:`davis_rig.models.default_detector_weights_path`). An
            ``.onnx`` path is resolved to the ``.safetensors`` beside it
            (same stem, or ``model_fp16.safetensors`` of a training export).
        device: torch device.

    Returns:
        :class:`~davis_rig.models.rvt.detector.RVTDetector`.

    Raises:
        MissingDependencyError: no path and the bundled weights are not installed (the message names the file).
        CheckpointError: unreadable checkpoint, or an ONNX file without torch weights beside it.
    """
    from davis_rig.models.rvt.checkpoint import load_detector

    if path is None:
        from davis_rig.models import default_detector_weights_path

        path = default_detector_weights_path()
    path = Path(path)
    if path.suffix.lower() == ".onnx":
        candidates = [path.with_suffix(".safetensors"), path.parent / "model_fp16.safetensors"]
        found = next((c for c in candidates if c.is_file()), None)
        if found is None:
            raise CheckpointError(f"{path} is an ONNX graph; the attack needs torch weights (expected one of "
                                  f"{[str(c) for c in candidates]}); pass --detector CHECKPOINT")
        path = found
    detector = load_detector(path).float()
    if device is not None:
        detector = detector.to(device)
    detector.eval()
    for p in detector.parameters():
        p.requires_grad_(False)
    return detector


def detector_fingerprint(detector) -> str:
    """A short hash of a detector's weights (names, shapes, dtypes and values of its state dict): what a resumed
    run checks against the one it was started with, so that textures are never credited to another detector.

    Returns:
        16 hex digits (the first 64 bits of a SHA-256).
    """
    import hashlib

    import torch

    digest = hashlib.sha256()
    for name, tensor in sorted(detector.state_dict().items()):
        value = tensor.detach().to("cpu").contiguous().reshape(-1)
        digest.update(f"{name}:{tuple(tensor.shape)}:{tensor.dtype}".encode())
        digest.update(value.view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()[:16]
