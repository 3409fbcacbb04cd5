#!/usr/bin/env python
"""Convert an RVT checkpoint (official Lightning .ckpt, .pt/.pth or .safetensors) to safetensors (+ ONNX step graph).

Usage: python tools/convert_checkpoint.py CKPT --out DIR [--config tiny|small|base|mini | --config-json PATH]
       [--onnx] [--verify] [--inert-unknown-globals]

Writes ``DIR/<stem>.safetensors`` (state dict without the ``mdl.`` prefix, config JSON in the metadata) and with
``--onnx`` ``DIR/<stem>_step.onnx`` (one recurrent step, dynamic batch). Prints the key report: entries read,
the architecture (given or inferred from the shapes), parameter count, the md5 of the source and whether it
matches a released Gen1 checkpoint. A checkpoint that does not fit the model prints the strict key/shape
report and exits with code 4. ``--config-json PATH`` gives any architecture as a JSON file that
:meth:`RVTConfig.from_dict` reads (``RVTConfig.to_json()`` output, or an official hydra ``model`` config): needed
for configs that are not presets, which the shapes cannot identify (``dim_head`` has no shape of its own).
``--verify`` runs 3 recurrent steps on seeded random histograms in PyTorch and onnxruntime and prints the
largest differences.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # pragma: no cover
    from davis_rig.models.rvt import RVTConfig

#: md5 prefixes of the released Gen1 checkpoints (uzh-rpg/RVT README).
RELEASED_MD5_PREFIXES = {"839317": "RVT-B gen1", "840f2b": "RVT-S gen1", "a770b9": "RVT-T gen1"}


@dataclass
class ConversionReport:
    """What :func:`convert` did (printed by :func:`main`).

    Attributes:
        source: the input checkpoint.
        md5: hex md5 of the input file.
        release: the released checkpoint whose md5 prefix matches, or ``None``.
        entries: state-dict entries read (after removing the ``mdl.`` prefix).
        parameters: number of parameter values (excluding BatchNorm buffers).
        config_name: the architecture's name, and how it was chosen (``given`` / ``inferred``).
        safetensors: the written safetensors file.
        onnx: the written ONNX file, or ``None``.
        verify: max abs differences PyTorch vs onnxruntime (``scores``, ``boxes``, ``boxes_rel``, ``states``).
    """

    source: Path
    md5: str
    release: str | None
    entries: int
    parameters: int
    config_name: str
    safetensors: Path
    onnx: Path | None = None
    verify: dict[str, float] = field(default_factory=dict)

    def lines(self) -> list[str]:
        """The human-readable report, one item per line."""
        release = f" (matches the released {self.release} checkpoint)" if self.release else ""
        out = [
            f"source:      {self.source} md5 {self.md5}{release}",
            f"keys:        {self.entries} state-dict entries, all matched the {self.config_name} model "
            f"(strict key and shape check), {self.parameters:,} parameters",
            f"safetensors: {self.safetensors}",
        ]
        if self.onnx is not None:
            out.append(f"onnx:        {self.onnx}")
        if self.verify:
            figures = ", ".join(f"{k} {v:.3g}" for k, v in self.verify.items())
            out.append(f"verify:      PyTorch vs onnxruntime over 3 steps, max abs diff: {figures}")
        return out


def _md5(path: Path) -> str:
    digest = hashlib.md5()
    with path.open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_config_json(path: str | Path) -> RVTConfig:
    """Read an architecture from a JSON file, as :meth:`RVTConfig.from_dict` accepts it.

    Args:
        path: JSON file: the flat dict of ``RVTConfig.to_dict()``, or an official hydra model config.

    Returns:
        The :class:`~davis_rig.models.rvt.RVTConfig`.

    Raises:
        OSError: the file cannot be read.
        FormatError: not JSON, or not a valid / supported RVT config (the message names the file).
    """
    from davis_rig.errors import FormatError
    from davis_rig.models.rvt import RVTConfig

    path = Path(path)
    try:
        return RVTConfig.from_dict(path.read_text(encoding="utf-8"))
    except FormatError as exc:
        raise FormatError(f"{path}: {exc}") from exc


def verify_onnx(model, onnx_path: Path, steps: int = 3, seed: int = 0) -> dict[str, float]:
    """Run ``steps`` recurrent steps on seeded random count histograms in PyTorch and onnxruntime.

    Returns:
        Max abs differences: ``scores`` (obj and class probs), ``boxes`` (px), ``boxes_rel`` (relative to
        max(|box|, 1)), ``states`` (LSTM h and c).
    """
    import numpy as np
    import torch

    from davis_rig.models.rvt.ort_runner import RVTOnnxRunner

    runner = RVTOnnxRunner(onnx_path)
    rng = np.random.default_rng(seed)
    torch_states = ort_states = None
    diffs = {"scores": 0.0, "boxes": 0.0, "boxes_rel": 0.0, "states": 0.0}
    channels, (height, width) = model.config.input_channels, model.config.in_res_hw
    for _ in range(steps):
        hist = np.zeros((1, channels, height, width), np.float32)
        hist[:, :, :240, :304] = np.minimum(rng.poisson(0.3, size=(1, channels, 240, 304)), 10)
        with torch.no_grad():
            decoded, torch_states = model(torch.from_numpy(hist), torch_states)
        ort_decoded, ort_states = runner.step(hist, ort_states)
        ref = decoded.numpy()
        box_err = np.abs(ort_decoded[..., :4] - ref[..., :4])
        diffs["scores"] = max(diffs["scores"], float(np.abs(ort_decoded[..., 4:] - ref[..., 4:]).max()))
        diffs["boxes"] = max(diffs["boxes"], float(box_err.max()))
        diffs["boxes_rel"] = max(diffs["boxes_rel"], float((box_err / np.maximum(np.abs(ref[..., :4]), 1)).max()))
        for (th, tc), (oh, oc) in zip(torch_states, ort_states):
            diffs["states"] = max(diffs["states"], float(np.abs(th.numpy() - oh).max()), float(np.abs(tc.numpy() - oc).max()))
    return diffs


def convert(
    checkpoint: str | Path,
    out_dir: str | Path,
    *,
    config: str | RVTConfig | None = None,
    onnx: bool = False,
    verify: bool = False,
    inert_unknown_globals: bool = False,
) -> ConversionReport:
    """Load ``checkpoint`` strictly, write safetensors (and optionally the ONNX step graph) into ``out_dir``.

    Args:
        checkpoint: ``.ckpt`` / ``.pt`` / ``.pth`` / ``.safetensors`` file.
        out_dir: output folder (created if missing).
        config: preset name (``tiny``, ``small``, ``base``, ``mini``) or an ``RVTConfig`` (e.g. from
            :func:`read_config_json`); default: inferred from the shapes.
        onnx: also export ``<stem>_step.onnx``.
        verify: compare PyTorch and onnxruntime on 3 steps (needs ``onnx``).
        inert_unknown_globals: see :func:`davis_rig.models.rvt.checkpoint.read_state_dict`.

    Returns:
        The report.

    Raises:
        CheckpointError: unreadable checkpoint or keys/shapes that do not fit (the readable report).
        ValueError: unknown preset name, or ``verify`` without ``onnx``.
    """
    from davis_rig.models.rvt import RVTConfig
    from davis_rig.models.rvt.checkpoint import load_detector, save_safetensors

    source = Path(checkpoint)
    presets = RVTConfig.presets()
    if config is not None and not isinstance(config, RVTConfig) and config not in presets:
        raise ValueError(f"config: expected one of {sorted(presets)} or an RVTConfig, got {config!r}")
    if verify and not onnx:
        raise ValueError("verify needs onnx=True")
    architecture = presets[config] if isinstance(config, str) else config
    model = load_detector(source, architecture, inert_unknown_globals=inert_unknown_globals)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    md5 = _md5(source)
    stem = source.name.split(".")[0]
    target = save_safetensors(
        model, out_dir / f"{stem}.safetensors", metadata={"source": source.name, "source_md5": md5}
    )
    report = ConversionReport(
        source=source,
        md5=md5,
        release=next((name for prefix, name in RELEASED_MD5_PREFIXES.items() if md5.startswith(prefix)), None),
        entries=len(model.state_dict()),
        parameters=sum(p.numel() for p in model.parameters()),
        config_name=f"{model.config.name} ({'inferred' if config is None else 'given'})",
        safetensors=target,
    )
    if onnx:
        from davis_rig.models.rvt.onnx_export import export_step_onnx

        report.onnx = export_step_onnx(model, out_dir / f"{stem}_step.onnx")
        if verify:
            report.verify = verify_onnx(model, report.onnx)
    return report


def main(argv: list[str] | None = None) -> int:
    """Parse arguments, run :func:`convert`, print the key report; returns the exit code."""
    from davis_rig.cli.common import add_out, new_parser, require, run_main

    parser = new_parser(Path(__file__).name, __doc__.splitlines()[0],
                        "examples:\n  python tools/convert_checkpoint.py rvt-b.ckpt --out models/ --onnx --verify\n")
    parser.add_argument("checkpoint", help="RVT checkpoint: .ckpt (Lightning), .pt/.pth or .safetensors")
    add_out(parser, metavar="DIR", aliases=("--out-dir",), help="output folder (created if missing)")
    architecture = parser.add_mutually_exclusive_group()
    architecture.add_argument(
        "--config", choices=["tiny", "small", "base", "mini"], help="preset architecture (default: from the shapes)"
    )
    architecture.add_argument(
        "--config-json",
        metavar="PATH",
        help="any architecture: a JSON file RVTConfig.from_dict reads (RVTConfig.to_json() or a hydra model config)",
    )
    parser.add_argument("--onnx", action="store_true", help="also export the one-step ONNX graph")
    parser.add_argument("--verify", action="store_true", help="with --onnx: compare PyTorch and onnxruntime")
    parser.add_argument(
        "--inert-unknown-globals",
        action="store_true",
        help="read a .ckpt whose pickle names non-tensor classes with them made inert (nothing is run)",
    )

    def check(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
        require(parser, args, "out", "--out")
        if args.verify and not args.onnx:
            parser.error("argument --verify: needs --onnx")

    def action(args: argparse.Namespace) -> int:
        report = convert(
            args.checkpoint,
            args.out,
            config=read_config_json(args.config_json) if args.config_json else args.config,
            onnx=args.onnx,
            verify=args.verify,
            inert_unknown_globals=args.inert_unknown_globals,
        )
        print("\n".join(report.lines()))
        return 0

    return run_main(parser, argv, action, check=check)


if __name__ == "__main__":
    sys.exit(main())
