"""Read RVT checkpoints safely (no code unpickled), check them strictly, build detectors, write safetensors.

Accepted files:

- ``.ckpt``: an official PyTorch-Lightning checkpoint; ``ckpt["state_dict"]`` holds the weights with the
  ``mdl.`` prefix. Read with ``torch.load(weights_only=True)``: a file that needs arbitrary classes or code
  to unpickle is refused with :class:`CheckpointError` (nothing of it is executed). Opt-in
  ``inert_unknown_globals=True`` reads such a file anyway with every unknown global replaced by an inert
  placeholder (:class:`InertGlobal`): for Lightning checkpoints whose optimizer/scheduler/callback state
  names classes or bound methods (the released RVT checkpoints may, see ARCHITECTURE.md §1).
- ``.pt`` / ``.pth``: a plain state dict (or a dict with ``state_dict``), with or without ``mdl.``.
- ``.safetensors``: a state dict (with or without ``mdl.``), or a reference fixture file whose weights are
  stored under ``state_dict.mdl.*``; the model config may be in the metadata key ``config`` (JSON).
"""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path
from typing import Mapping

from davis_rig.errors import CheckpointError, FormatError
from davis_rig.models.rvt._torch import torch
from davis_rig.models.rvt.config import RVTConfig
from davis_rig.models.rvt.detector import RVTDetector

#: Prefix of the network weights inside an official Lightning ``state_dict``.
LIGHTNING_PREFIX = "mdl."
#: Prefix of the network weights in the reference fixture files.
FIXTURE_PREFIX = "state_dict.mdl."
#: ``format`` written by :func:`save_safetensors` into the safetensors metadata.
SAFETENSORS_FORMAT = "davis_rig-rvt-state-dict/1"
#: ``format`` of davis-train's ``checkpoints/last.pt`` (the trainer writes this constant): the full training
#: state, network weights under ``"model"``.
TRAIN_CHECKPOINT_FORMAT = "davis_rig-train-checkpoint/1"

_TORCH_SUFFIXES = (".ckpt", ".pt", ".pth")
_REPORT_MAX_LINES = 20


def _strip_prefix(state_dict: Mapping[str, object]) -> dict[str, object]:
    """Drop the Lightning ``mdl.`` (or fixture ``state_dict.mdl.``) prefix; other keys are kept as they are."""
    for prefix in (FIXTURE_PREFIX, LIGHTNING_PREFIX):
        if any(key.startswith(prefix) for key in state_dict):
            if prefix == FIXTURE_PREFIX:  # fixture files also hold inputs/outputs: keep only the weights
                return {key[len(prefix) :]: value for key, value in state_dict.items() if key.startswith(prefix)}
            return {(key[len(prefix) :] if key.startswith(prefix) else key): value for key, value in state_dict.items()}
    return dict(state_dict)


def _last_line(text: str) -> str:
    lines = [line.strip() for line in text.splitlines() if line.strip() and not line.startswith("Check the doc")]
    return lines[-1][:300] if lines else ""


class InertGlobal:
    """Stand-in for a class or function referenced by a checkpoint pickle in ``inert_unknown_globals`` mode.

    Calling it (pickle REDUCE/NEWOBJ) only records the arguments; ``__setstate__`` only records the state.
    Nothing named by the pickle is imported or executed.
    """

    qualified_name = "?"

    def __init__(self, *args, **kwargs):
        self.args = args
        self.kwargs = kwargs

    def __setstate__(self, state):
        self.state = state

    def __repr__(self) -> str:
        return f"<inert {self.qualified_name}>"


def _inert_pickle_module():
    """A ``pickle_module`` for ``torch.load`` that resolves only torch's weights-only allow-list.

    Every other global becomes a fresh :class:`InertGlobal` subclass, so loading never imports or runs code
    named by the file; tensors are rebuilt by the same functions ``weights_only=True`` allows.
    """
    import pickle
    import types

    try:
        from torch._weights_only_unpickler import _get_allowed_globals

        allowed = dict(_get_allowed_globals())
    except (ImportError, AttributeError):  # pragma: no cover - older/newer torch without the private helper
        import collections

        allowed = {"collections.OrderedDict": collections.OrderedDict}
        for name in ("_rebuild_tensor", "_rebuild_tensor_v2", "_rebuild_tensor_v3", "_rebuild_parameter"):
            if hasattr(torch._utils, name):
                allowed[f"torch._utils.{name}"] = getattr(torch._utils, name)

    class InertUnpickler(pickle.Unpickler):
        def find_class(self, module, name):
            found = allowed.get(f"{module}.{name}")
            if found is not None:
                return found
            if module == "torch" and isinstance(getattr(torch, name, None), torch.dtype):
                return getattr(torch, name)
            return type(f"Inert_{name}", (InertGlobal,), {"qualified_name": f"{module}.{name}"})

    module = types.ModuleType("davis_rig_inert_pickle")
    module.Unpickler = InertUnpickler
    module.load = lambda file, **kwargs: InertUnpickler(file, **kwargs).load()
    module.__version__ = pickle.format_version
    return module


def _read_torch_file(path: Path, inert_unknown_globals: bool = False) -> dict[str, torch.Tensor]:
    if inert_unknown_globals:
        import zipfile

        if not zipfile.is_zipfile(path):
            raise CheckpointError(
                f"{path}: inert_unknown_globals needs the zip checkpoint format (torch >= 1.6); "
                f"this file is not a zip archive (legacy format or corrupt)"
            )
    try:
        if inert_unknown_globals:
            obj = torch.load(str(path), map_location="cpu", weights_only=False, pickle_module=_inert_pickle_module())
        else:
            obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises UnpicklingError, RuntimeError, EOFError, ... depending on the damage
        text = str(exc)
        blocked = re.search(r"GLOBAL ([\w.]+)", text)
        if blocked is not None:
            raise CheckpointError(
                f"{path}: refused to unpickle: torch.load(weights_only=True) does not allow the global "
                f"{blocked.group(1)!r} (the pickle references code or a custom class; nothing was executed). "
                f"To extract only the weights, pass inert_unknown_globals=True (unknown globals become inert "
                f"placeholders, nothing is imported or run), or re-save the state_dict in a trusted environment"
            ) from exc
        raise CheckpointError(
            f"{path}: not a readable PyTorch checkpoint (corrupt or truncated?): {type(exc).__name__}: "
            f"{_last_line(text)}"
        ) from exc
    if isinstance(obj, Mapping) and isinstance(obj.get("state_dict"), Mapping):
        obj = obj["state_dict"]
    elif isinstance(obj, Mapping) and obj.get("format") == TRAIN_CHECKPOINT_FORMAT:
        if not isinstance(obj.get("model"), Mapping):
            raise CheckpointError(f"{path}: {TRAIN_CHECKPOINT_FORMAT} file without model weights")
        obj = obj["model"]  # the raw training weights (an EMA, if any, is in best.safetensors / the export)
    if not isinstance(obj, Mapping):
        raise CheckpointError(f"{path}: expected a state dict (mapping of name → tensor), got {type(obj).__name__}")
    return _strip_prefix(obj)


def _read_safetensors(path: Path) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(str(path), framework="pt") as handle:
            metadata = dict(handle.metadata() or {})
            keys = list(handle.keys())
            if any(key.startswith(FIXTURE_PREFIX) for key in keys):
                keys = [key for key in keys if key.startswith(FIXTURE_PREFIX)]
            tensors = {key: handle.get_tensor(key) for key in keys}
    except (SafetensorError, OSError, ValueError) as exc:
        raise CheckpointError(f"{path}: not a readable safetensors file ({exc})") from exc
    return _strip_prefix(tensors), metadata


def read_state_dict(path: str | Path, *, inert_unknown_globals: bool = False) -> dict[str, torch.Tensor]:
    """Read the detector weights of a checkpoint, without the ``mdl.`` prefix.

    Args:
        path: ``.ckpt`` (Lightning), ``.pt``/``.pth`` (plain state dict, or davis-train's ``checkpoints/last.pt``:
            its raw training weights) or ``.safetensors`` file.
        inert_unknown_globals: for ``.ckpt``/``.pt``/``.pth``: instead of refusing a pickle that references
            classes or functions outside torch's weights-only allow-list (e.g. a Lightning checkpoint whose
            scheduler state holds a bound method), load it with every such global replaced by an inert
            :class:`InertGlobal` placeholder. Nothing named by the file is imported or executed; only the
            tensors are used.

    Returns:
        name → tensor (CPU), names as in ``RVTDetector.state_dict()``.

    Raises:
        CheckpointError: missing or unreadable file, a pickle that needs code (``weights_only`` refused), or
            content that is not a mapping of tensors.
    """
    return _read_with_metadata(Path(path), inert_unknown_globals)[0]


def _read_with_metadata(
    path: Path, inert_unknown_globals: bool = False
) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    if not path.is_file():
        raise CheckpointError(f"{path}: checkpoint file not found")
    suffix = path.suffix.lower()
    if suffix == ".safetensors":
        state_dict, metadata = _read_safetensors(path)
    elif suffix in _TORCH_SUFFIXES:
        state_dict, metadata = _read_torch_file(path, inert_unknown_globals), {}
    else:
        raise CheckpointError(
            f"{path}: unknown checkpoint type {suffix!r}; expected one of .ckpt, .pt, .pth, .safetensors"
        )
    not_tensors = sorted(key for key, value in state_dict.items() if not isinstance(value, torch.Tensor))
    if not_tensors:
        raise CheckpointError(f"{path}: entries that are not tensors: {not_tensors[:_REPORT_MAX_LINES]}")
    if not state_dict:
        raise CheckpointError(f"{path}: no weights found")
    return state_dict, metadata


def _shape(state_dict: Mapping[str, torch.Tensor], key: str) -> tuple[int, ...] | None:
    tensor = state_dict.get(key)
    return None if tensor is None else tuple(tensor.shape)


def infer_config(state_dict: Mapping[str, torch.Tensor], metadata: Mapping[str, str] | None = None) -> RVTConfig:
    """Infer the architecture of a checkpoint.

    A ``config`` JSON in ``metadata`` wins. Otherwise the shapes give embed_dim, stage dims, input channels,
    classes and FPN depth, and the result must equal one of the :meth:`RVTConfig.presets` (tiny, small, base,
    mini, nano), which fix ``dim_head`` (it has no shape of its own).

    Args:
        state_dict: weights without the ``mdl.`` prefix.
        metadata: safetensors metadata, if any.

    Returns:
        The config.

    Raises:
        CheckpointError: shapes that match no preset (pass ``config=`` explicitly) or a bad metadata config.
    """
    if metadata and metadata.get("config"):
        try:
            return RVTConfig.from_dict(metadata["config"])
        except FormatError as exc:
            raise CheckpointError(f"checkpoint metadata 'config' is not a usable RVT config: {exc}") from exc
    stem = _shape(state_dict, "backbone.stages.0.downsample_cf2cl.conv.weight")
    dims = [_shape(state_dict, f"backbone.stages.{s}.downsample_cf2cl.conv.weight") for s in range(4)]
    cls_pred = _shape(state_dict, "yolox_head.cls_preds.0.weight")
    if stem is None or None in dims or cls_pred is None:
        raise CheckpointError(
            "cannot infer the RVT variant: the checkpoint lacks backbone.stages.{0..3}.downsample_cf2cl.conv.weight "
            "or yolox_head.cls_preds.0.weight (is this an RVT detector checkpoint?)"
        )
    embed_dim, input_channels = stem[0], stem[1]
    multiplier = tuple(shape[0] // embed_dim for shape in dims)
    bottlenecks = len({key.split(".")[3] for key in state_dict if key.startswith("fpn.C3_p4.m.")})
    blocks = tuple(
        len({key.split(".")[4] for key in state_dict if key.startswith(f"backbone.stages.{s}.att_blocks.")})
        for s in range(4)
    )
    found = {
        "embed_dim": embed_dim,
        "dim_multiplier": multiplier,
        "num_blocks": blocks,
        "input_channels": input_channels,
        "num_classes": cls_pred[0],
        "fpn_num_bottlenecks": bottlenecks,
    }
    for preset in RVTConfig.presets().values():
        candidate = replace(preset, num_classes=cls_pred[0], input_channels=input_channels)
        if (
            candidate.embed_dim == embed_dim
            and candidate.dim_multiplier == multiplier
            and candidate.num_blocks == blocks
            and candidate.fpn_num_bottlenecks == bottlenecks
        ):
            return candidate
    raise CheckpointError(
        f"cannot infer the RVT variant from the shapes {found}: they match none of the presets "
        f"{sorted(RVTConfig.presets())} (dim_head cannot be read from shapes); pass config=RVTConfig(...) explicitly"
    )


def check_state_dict(
    model: torch.nn.Module, state_dict: Mapping[str, torch.Tensor], *, source: str = "checkpoint"
) -> None:
    """Strict key and shape check of ``state_dict`` against ``model.state_dict()``.

    Raises:
        CheckpointError: with a readable report listing missing keys, unexpected keys and shape mismatches
            (each list cut at 20 lines, with counts).
    """
    expected = model.state_dict()
    missing = [key for key in expected if key not in state_dict]
    unexpected = [key for key in state_dict if key not in expected]
    mismatched = [
        f"{key}: model {tuple(expected[key].shape)}, {source} {tuple(state_dict[key].shape)}"
        for key in expected
        if key in state_dict and tuple(expected[key].shape) != tuple(state_dict[key].shape)
    ]
    if not (missing or unexpected or mismatched):
        return
    name = getattr(getattr(model, "config", None), "name", type(model).__name__)
    lines = [
        f"{source} does not match the {name} model ({len(expected)} entries expected, {len(state_dict)} found): "
        f"{len(missing)} missing, {len(unexpected)} unexpected, {len(mismatched)} with a different shape"
    ]
    for title, items in (("missing", missing), ("unexpected", unexpected), ("shape mismatch", mismatched)):
        if items:
            lines.append(f"  {title} ({len(items)}):")
            lines.extend(f"    {item}" for item in items[:_REPORT_MAX_LINES])
            if len(items) > _REPORT_MAX_LINES:
                lines.append(f"    ... and {len(items) - _REPORT_MAX_LINES} more")
    raise CheckpointError("\n".join(lines))


def load_detector(
    path: str | Path, config: RVTConfig | None = None, *, inert_unknown_globals: bool = False
) -> RVTDetector:
    """Build an :class:`RVTDetector` from a checkpoint file, in eval mode, on the CPU.

    Args:
        path: ``.ckpt`` / ``.pt`` / ``.pth`` / ``.safetensors`` (see :func:`read_state_dict`).
        config: the architecture; default: the metadata ``config`` if present, else inferred from the
            shapes (the tiny/small/base/mini/nano presets, see :func:`infer_config`).
        inert_unknown_globals: see :func:`read_state_dict` (off: such pickles are refused).

    Returns:
        The detector with the weights loaded (float32 parameters; other float dtypes are converted).

    Raises:
        CheckpointError: unreadable file, unknown variant, keys/shapes that do not match (readable report), or
            weights holding NaN or inf; the message names ``path``.
    """
    path = Path(path)
    state_dict, metadata = _read_with_metadata(path, inert_unknown_globals)
    if config is None:
        try:
            config = infer_config(state_dict, metadata)
        except CheckpointError as exc:
            raise CheckpointError(f"{path}: {exc}") from None
    damaged = sorted(key for key, value in state_dict.items()
                     if hasattr(value, "is_floating_point") and value.is_floating_point()
                     and not bool(value.isfinite().all()))
    if damaged:
        raise CheckpointError(f"{path}: {len(damaged)} weight tensors hold NaN or inf (e.g. {', '.join(damaged[:3])}): "
                              "the checkpoint is damaged (scored, it would read as a perfect attack)")
    model = RVTDetector(config)
    try:
        check_state_dict(model, state_dict, source=str(path))
    except CheckpointError as exc:
        try:
            actual = infer_config(state_dict, metadata).name
        except CheckpointError:
            raise exc from None
        raise CheckpointError(f"{exc}\n  hint: the checkpoint's shapes match {actual}") from None
    model.load_state_dict(state_dict, strict=True)
    return model.eval()


def save_safetensors(model: RVTDetector, path: str | Path, metadata: Mapping[str, str] | None = None) -> Path:
    """Write the detector's state dict (no ``mdl.`` prefix) to a safetensors file with its config.

    Args:
        model: the detector.
        path: output file (``.safetensors``).
        metadata: extra str → str entries (``config`` and ``format`` are set by this function).

    Returns:
        The path written.

    Raises:
        FormatError: a non-string metadata value.
    """
    from safetensors.torch import save_file

    path = Path(path)
    extra = dict(metadata or {})
    bad = sorted(key for key, value in extra.items() if not isinstance(key, str) or not isinstance(value, str))
    if bad:
        raise FormatError(f"save_safetensors: metadata values must be str, got non-str for {bad}")
    extra["config"] = model.config.to_json()
    extra["format"] = SAFETENSORS_FORMAT
    tensors = {key: value.detach().to("cpu").contiguous() for key, value in model.state_dict().items()}
    save_file(tensors, str(path), metadata=extra)
    return path


def metadata_config(path: str | Path) -> RVTConfig | None:
    """The ``config`` stored in a safetensors file's metadata, or ``None`` (no torch tensors are read)."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as handle:
        raw = (handle.metadata() or {}).get("config")
    return None if raw is None else RVTConfig.from_dict(json.loads(raw))
