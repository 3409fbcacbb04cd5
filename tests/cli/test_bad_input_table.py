"""Every command and tools/*.py × {nonexistent file, wrong file type, out-of-range, NaN, conflicting options,
missing dependency, Ctrl-C}, where the command has such an input.

Each row: the documented exit code, exactly one ``<command>: error: ...`` line (or ``<command>: interrupted``),
the last on stderr (argparse's usage lines may come before it), naming the option or the file, no traceback, and
nothing half-written: the inputs unchanged, nothing at all left in the test's own folder (where every output goes)
and no staging file. Ctrl-C is a ``KeyboardInterrupt`` raised inside the command's work (for ``davis-record`` and
the ``davis-view`` server a Ctrl-C is a clean stop instead; tests/cli/test_ctrl_c.py sends real SIGINTs to
running commands). ``pytest tests/cli/test_bad_input_table.py --cli-table FILE`` writes the observed table as
markdown.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest

import numpy as np

from davis_rig.cli import attack, eval_dataset, export, info, label, make_dataset, quantize, record, train, view
from davis_rig.cli import eval as eval_cli
from davis_rig.labelers.session_labels import label_session

from tests.helpers.eval_data import person_rvt, person_yolo, scene_session, sha256

COMMANDS = {"davis-record": record.main, "davis-label": label.main, "davis-eval": eval_cli.main,
            "davis-eval-dataset": eval_dataset.main, "davis-train": train.main,
            "davis-make-dataset": make_dataset.main, "davis-info": info.main, "davis-export": export.main,
            "davis-view": view.main, "davis-attack": attack.main, "davis-quantize": quantize.main}
#: The scripts of tools/ that take arguments (each gets rows below; ``tools/x.py`` runs ``x.main``).
TOOLS = ("aedat4_to_session", "aps_attack", "capture_replay", "contact_sheet", "convert_checkpoint",
         "export_body_asset", "make_sample_replay", "make_sample_session", "make_trigger_victim", "measure_labeler",
         "probe_texture_sensitivity", "score_validation_clips", "ship_detector",
         "trigger_feature_probe", "trigger_gradient_check", "usb_stop_stress", "victim_controls")


@dataclass
class Row:
    """One bad input: ``argv`` gets the files of :func:`files` by name (``{session}``, ``{out}``, ...)."""

    command: str
    case: str
    argv: list[str]
    code: int
    message: str
    interrupt: str | None = None  # "module.attribute" replaced by a function raising KeyboardInterrupt
    created: list[str] = field(default_factory=list)  # paths outside the test's folder that must not exist after
    missing_module: str | None = None  # a module made unimportable (the missing optional dependency)

    @property
    def prog(self) -> str:
        """The name the messages start with: ``davis-attack optimize``, ``aps_attack.py``."""
        if self.command == "davis-attack":
            return f"{self.command} {self.argv[0]}"
        return self.command.removeprefix("tools/")


def _interrupt(*args, **kwargs):
    raise KeyboardInterrupt


def _interrupt_after_mkdir(path_argument: int) -> Callable:
    """A stand-in of an API call that creates its output folders, then gets Ctrl-C."""

    def call(*args, **kwargs):
        (Path(args[path_argument]) / "checkpoints").mkdir(parents=True)
        raise KeyboardInterrupt

    return call


ROWS = [
    # davis-record
    Row("davis-record", "nonexistent file", ["--fake", "{missing}", "--out", "{out}.h5", "-q"], 4,
        "missing.davisreplay: no such replay file", created=["{out}.h5"]),
    Row("davis-record", "wrong file type", ["--fake", "{text}", "--out", "{out}.h5", "-q"], 4, "text.h5",
        created=["{out}.h5"]),
    Row("davis-record", "out of range", ["--usb-transfers", "-1", "--out", "{out}.h5"], 2,
        "argument --usb-transfers: expected an integer >= 0, got '-1'", created=["{out}.h5"]),
    Row("davis-record", "nan", ["--duration", "nan", "--out", "{out}.h5"], 2,
        "argument --duration: expected a finite number, got 'nan'", created=["{out}.h5"]),
    Row("davis-record", "conflicting options", ["--recover", "{session}", "--out", "{out}.h5"], 2,
        "argument --recover: not allowed with --out", created=["{out}.h5"]),
    Row("davis-record", "Ctrl-C", ["--fake", "{replay}", "--out", "{out}.h5", "-q"], 130, "interrupted",
        interrupt="davis_rig.cli.record.fake_backend", created=["{out}.h5"]),
    # davis-label
    Row("davis-label", "nonexistent file", ["{missing}", "--yolo", "{yolo}", "-q"], 4, "no such session file"),
    Row("davis-label", "wrong file type", ["{text}", "--yolo", "{yolo}", "-q"], 4, "cannot open as HDF5"),
    Row("davis-label", "out of range", ["{session}", "--yolo", "{yolo}", "--conf", "1.5"], 2,
        "argument --conf: expected a number in [0, 1], got '1.5'"),
    Row("davis-label", "nan", ["{session}", "--yolo", "{yolo}", "--iou", "nan"], 2,
        "argument --iou: expected a finite number, got 'nan'"),
    Row("davis-label", "conflicting options", ["{session}", "--yolo", "{yolo}", "--crop-origin", "500", "500"], 2,
        "argument --crop-origin: the 304x240 crop at (500, 500) leaves the 346x260 sensor"),
    Row("davis-label", "Ctrl-C", ["{session}", "--yolo", "{yolo}", "-q"], 130, "interrupted",
        interrupt="davis_rig.labelers.session_labels.label_frames"),
    # davis-eval
    Row("davis-eval", "nonexistent file", ["{missing}", "--detector", "{rvt}", "-q", "--out", "{out}"], 4,
        "no such session file", created=["{out}"]),
    Row("davis-eval", "wrong file type", ["{labelled}", "--detector", "{text}", "-q", "--out", "{out}"], 4,
        "text.h5", created=["{out}"]),
    Row("davis-eval", "out of range", ["{session}", "--seq-len", "0"], 2,
        "argument --seq-len: expected an integer >= 1, got '0'"),
    Row("davis-eval", "nan", ["{session}", "--skip-first-ms", "nan"], 2,
        "argument --skip-first-ms: expected a finite number, got 'nan'"),
    Row("davis-eval", "conflicting options", ["{session}", "--threshold", "0.25", "--gif-threshold", "0.5"], 2,
        "argument --gif-threshold: 0.5 is not one of the scored thresholds 0.25"),
    Row("davis-eval", "Ctrl-C", ["{labelled}", "--detector", "{rvt}", "-q", "--out", "{out}"], 130, "interrupted",
        interrupt="davis_rig.evaluation.physical.score_session", created=["{out}"]),
    # davis-eval-dataset
    Row("davis-eval-dataset", "nonexistent file", ["{missing}", "-q", "--out", "{out}.json"], 4,
        "no such split folder", created=["{out}.json"]),
    Row("davis-eval-dataset", "wrong file type", ["{text}", "-q", "--out", "{out}.json"], 4, "no such split folder",
        created=["{out}.json"]),
    Row("davis-eval-dataset", "out of range", ["{dir}", "--lanes", "0"], 2,
        "argument --lanes: expected an integer >= 1, got '0'"),
    Row("davis-eval-dataset", "nan", ["{dir}", "--threshold", "nan"], 2,
        "argument --threshold: expected a finite number, got 'nan'"),
    Row("davis-eval-dataset", "conflicting options", ["{dir}", "--threshold", "0,0.5"], 2,
        "argument --threshold: expected values in (0, 1), got (0.0, 0.5)"),
    Row("davis-eval-dataset", "Ctrl-C", ["{dir}", "-q", "--out", "{out}.json"], 130, "interrupted",
        interrupt="davis_rig.training.evaluate.evaluate_split", created=["{out}.json"]),
    # davis-train
    Row("davis-train", "nonexistent file", ["{missing}", "--out", "{out}", "-q"], 4, "no such split folder",
        created=["{out}"]),
    Row("davis-train", "wrong file type", ["{text}", "--out", "{out}", "-q"], 4, "no such split folder",
        created=["{out}"]),
    Row("davis-train", "out of range", ["{dir}", "--out", "{out}", "--steps", "0"], 2,
        "argument --steps: expected an integer >= 1, got '0'", created=["{out}"]),
    Row("davis-train", "nan", ["{dir}", "--out", "{out}", "--lr", "nan"], 2,
        "argument --lr: expected a finite number, got 'nan'", created=["{out}"]),
    Row("davis-train", "conflicting options", ["{dir}", "--out", "{out}", "--batch", "1", "--sampling", "mixed"], 2,
        "argument --batch: sampling 'mixed' needs ≥ 2", created=["{out}"]),
    Row("davis-train", "Ctrl-C", ["{dir}", "--out", "{out}", "-q"], 130, "interrupted",
        interrupt="davis_rig.training.trainer.train", created=["{out}"]),
    # davis-make-dataset (no input file: its output folder is the file argument; below a file, or a file itself)
    Row("davis-make-dataset", "nonexistent file", ["--out", "{text}/dataset", "--sequences", "3", "-q"], 4,
        "text.h5/dataset: not a directory"),
    Row("davis-make-dataset", "wrong file type", ["--out", "{text}", "--sequences", "3", "-q"], 4, "text.h5"),
    Row("davis-make-dataset", "out of range", ["--out", "{out}", "--sequences", "0"], 2,
        "argument --sequences: expected an integer >= 1, got '0'", created=["{out}"]),
    Row("davis-make-dataset", "nan", ["--out", "{out}", "--sequences", "3", "--test-scale-probability", "nan"], 2,
        "argument --test-scale-probability: expected a finite number, got 'nan'", created=["{out}"]),
    Row("davis-make-dataset", "conflicting options", ["{out}", "--out", "{out}", "--sequences", "3"], 2,
        "argument --out: not allowed with a positional OUT_DIR", created=["{out}"]),
    Row("davis-make-dataset", "Ctrl-C", ["--out", "{out}", "--sequences", "3", "-q"], 130, "interrupted",
        interrupt="davis_rig.training.synthetic.generate_dataset", created=["{out}"]),
    # davis-quantize
    Row("davis-quantize", "nonexistent file", ["--detector", "{rvt}", "--calibration", "{missing}", "--out",
                                               "{out}.onnx", "-q"], 4, "missing.davisreplay: no such file or folder",
        created=["{out}.onnx"]),
    Row("davis-quantize", "wrong file type", ["--detector", "{text}", "--calibration", "{session}", "--out",
                                              "{out}.onnx", "-q"], 4, "text.h5", created=["{out}.onnx"]),
    Row("davis-quantize", "out of range", ["--calibration", "{session}", "--out", "{out}.onnx", "--windows", "0"], 2,
        "argument --windows: expected an integer >= 1, got '0'", created=["{out}.onnx"]),
    Row("davis-quantize", "nan", ["--calibration", "{session}", "--out", "{out}.onnx", "--seconds", "nan"], 2,
        "argument --seconds: expected a finite number, got 'nan'", created=["{out}.onnx"]),
    Row("davis-quantize", "conflicting options", ["--detector", "{rvt}", "--calibration", "{session}", "--out",
                                                  "{rvt}"], 2, "argument --out: must differ from --detector"),
    Row("davis-quantize", "Ctrl-C", ["--detector", "{rvt}", "--calibration", "{session}", "--out", "{out}.onnx",
                                     "-q"], 130, "interrupted",
        interrupt="davis_rig.models.rvt.quantize.quantize_step_onnx", created=["{out}.onnx"]),
    # davis-info (no numeric option: nothing out of range, no NaN, no conflicting options)
    Row("davis-info", "nonexistent file", ["{missing}"], 4, "missing.davisreplay: no such session file"),
    Row("davis-info", "wrong file type", ["{text}"], 4, "text.h5: not a session.h5: not an HDF5 file"),
    Row("davis-info", "a folder", ["{dir}"], 4, "empty_dir: not a file"),
    Row("davis-info", "one bad file of two", ["{session}", "{missing}"], 4, "missing.davisreplay: no such session"),
    # davis-export
    Row("davis-export", "nonexistent file", ["{missing}", "--to", "npz", "--out", "{out}.npz"], 4,
        "missing.davisreplay: no such session file"),
    Row("davis-export", "wrong file type", ["{text}", "--to", "npz", "--out", "{out}.npz"], 4,
        "text.h5: cannot open as HDF5"),
    Row("davis-export", "out of range", ["{session}", "--to", "npz", "--out", "{out}.npz", "--crop-origin", "500",
                                         "500"], 2, "argument --crop-origin: the 304x240 crop at (500, 500)"),
    Row("davis-export", "nan", ["{session}", "--to", "npz", "--out", "{out}.npz", "--crop-origin", "nan", "0"], 2,
        "argument --crop-origin: expected an integer, got 'nan'"),
    Row("davis-export", "conflicting options", ["{session}", "--to", "npz", "--out", "{out}.npz", "--split", "val"],
        2, "argument --split: applies to --to rvt only"),
    Row("davis-export", "output exists", ["{session}", "--to", "npz", "--out", "{text}"], 4,
        "text.h5: file exists (pass overwrite=True / --overwrite"),
    Row("davis-export", "missing dependency", ["{session}", "--to", "aedat4", "--out", "{out}.aedat4", "-q"], 5,
        "davis_rig[aedat4]", missing_module="dv_processing"),
    Row("davis-export", "Ctrl-C", ["{labelled}", "--to", "npz", "--out", "{out}.npz", "-q"], 130, "interrupted",
        interrupt="davis_rig.interop.npz._write_member"),
    # davis-view
    Row("davis-view", "nonexistent file", ["{missing}", "--no-detector", "--export", "{out}.gif"], 4,
        "missing.davisreplay: no such session file"),
    Row("davis-view", "wrong file type", ["{text}", "--no-detector", "--export", "{out}.gif"], 4,
        "text.h5: cannot open as HDF5"),
    Row("davis-view", "wrong detector type", ["{session}", "--detector", "{text}", "--export", "{out}.gif"], 4,
        "text.h5: davis-view scores with onnxruntime and needs an RVT step ONNX"),
    Row("davis-view", "out of range", ["{session}", "--port", "70000"], 2,
        "argument --port: expected an integer in [0, 65535], got '70000'"),
    Row("davis-view", "nan", ["{session}", "--export", "{out}.gif", "--fps", "nan"], 2,
        "argument --fps: expected a finite number, got 'nan'"),
    Row("davis-view", "conflicting options", ["{session}", "--no-detector", "--detector", "{rvt}"], 2,
        "argument --no-detector: not allowed with --detector"),
    Row("davis-view", "wrong output type", ["{session}", "--export", "{out}.txt"], 2,
        "argument --export: expected a .mp4 or .gif file"),
    Row("davis-view", "Ctrl-C", ["{session}", "--no-detector", "--export", "{out}.gif", "-q"], 130, "interrupted",
        interrupt="davis_rig.viewer.export.export_video"),
    # davis-attack optimize / search / evaluate / reproduce / export
    Row("davis-attack", "nonexistent file", ["optimize", "--out", "{out}", "--detector", "{missing}", "--cells", "2",
                                             "--device", "cpu", "-q"], 4,
        "missing.davisreplay: checkpoint file not found"),
    Row("davis-attack", "wrong file type", ["optimize", "--out", "{out}", "--detector", "{text}", "--device", "cpu",
                                            "-q"], 4, "text.h5: unknown checkpoint type '.h5'"),
    Row("davis-attack", "wrong file type", ["optimize", "--out", "{out}", "--start", "{text}", "--cells", "2",
                                            "--device", "cpu", "-q"], 4, "text.h5"),
    Row("davis-attack", "out of range", ["optimize", "--out", "{out}", "--cells", "0"], 2,
        "argument --cells: expected an integer >= 1, got '0'"),
    Row("davis-attack", "nan", ["optimize", "--out", "{out}", "--lr", "nan"], 2,
        "argument --lr: expected a finite number, got 'nan'"),
    Row("davis-attack", "conflicting options", ["optimize", "--out", "{out}", "--lr", "1e-3", "--lr-min", "1e-2"], 2,
        "argument --lr-min: 0.01 exceeds --lr 0.001"),
    Row("davis-attack", "nonexistent file", ["search", "--out", "{out}", "--detector", "{missing}", "--device", "cpu",
                                             "-q"], 4, "missing.davisreplay: checkpoint file not found"),
    Row("davis-attack", "wrong file type", ["search", "--out", "{out}", "--trigger", "{text}", "-q"], 4,
        "text.h5: not a readable image"),
    Row("davis-attack", "wrong file type", ["search", "--out", "{out}", "--start", "{text}", "-q"], 4,
        "text.h5: not a readable image"),
    Row("davis-attack", "wrong shape", ["search", "--out", "{out}", "--start", "{texture}", "-q"], 4,
        "--start is a 4x4 grid, the run's --cells is 10"),
    Row("davis-attack", "out of range", ["search", "--out", "{out}", "--smoothing", "0"], 2,
        "argument --smoothing: expected a number in (0, 1], got '0'"),
    Row("davis-attack", "out of range", ["search", "--out", "{out}", "--start-confidence", "1"], 2,
        "argument --start-confidence: expected a number in [0.5, 1), got '1'"),
    Row("davis-attack", "nan", ["search", "--out", "{out}", "--floor", "nan"], 2,
        "argument --floor: expected a finite number, got 'nan'"),
    Row("davis-attack", "unknown name", ["search", "--out", "{out}", "--parts", "nose"], 2,
        "argument --parts: invalid choice: 'nose'"),
    Row("davis-attack", "conflicting options", ["search", "--out", "{out}", "--elite", "13"], 2,
        "argument --elite: 13 is more than --population 12"),
    Row("davis-attack", "conflicting options", ["search", "--out", "{out}", "--clips-per-grid", "40"], 2,
        "argument --clips-per-grid: 40 is more than --pool-clips 32"),
    Row("davis-attack", "Ctrl-C", ["search", "--out", "{out}", "--device", "cpu", "-q"], 130, "interrupted",
        interrupt="davis_rig.attack.search.search_texture", created=["{out}"]),
    Row("davis-attack", "nonexistent file", ["evaluate", "--out", "{out}", "--texture", "a={missing}", "--device",
                                             "cpu", "-q"], 4, "texture not found: {missing}"),
    Row("davis-attack", "wrong file type", ["evaluate", "--out", "{out}", "--texture", "a={text}", "--device", "cpu",
                                            "-q"], 4, "text.h5: not a readable image"),
    Row("davis-attack", "out of range", ["evaluate", "--out", "{out}", "--texture", "a={texture}", "--cells", "0"], 2,
        "argument --cells: expected an integer >= 1, got '0'"),
    Row("davis-attack", "nan", ["evaluate", "--out", "{out}", "--texture", "a={texture}", "--threshold", "nan"], 2,
        "argument --threshold: expected a finite number, got 'nan'"),
    Row("davis-attack", "conflicting options", ["evaluate", "--out", "{out}", "--table", "1", "--texture",
                                                "a={texture}"], 2, "argument --texture: Table 1 keys are grid sizes"),
    Row("davis-attack", "output is a file", ["evaluate", "--out", "{text}", "--texture", "a={texture}", "--device",
                                             "cpu", "-q"], 4, "text.h5: --out needs a folder, and"),
    Row("davis-attack", "wrong shape", ["evaluate", "--out", "{out}", "--table", "1", "--texture", "10={texture}",
                                        "--device", "cpu", "-q"], 4,
        "--texture: Table 1 keys are grid sizes, and these grids have other shapes"),
    Row("davis-attack", "unknown name", ["evaluate", "--out", "{out}", "--table", "2", "--texture", "foo={texture}"],
        2, "argument --texture: Table 2 keys are part combinations"),
    Row("davis-attack", "nonexistent file", ["reproduce", "--table", "1", "--out", "{out}", "--detector", "{missing}",
                                             "--device", "cpu", "-q"], 4,
        "missing.davisreplay: checkpoint file not found"),
    Row("davis-attack", "wrong file type", ["reproduce", "--table", "1", "--out", "{out}", "--detector", "{text}",
                                            "--device", "cpu", "-q"], 4, "text.h5: unknown checkpoint type '.h5'"),
    Row("davis-attack", "out of range", ["reproduce", "--table", "1", "--out", "{out}", "--grids", "300"], 2,
        "argument --grids: expected an integer in [1, 256], got '300'"),
    Row("davis-attack", "nan", ["reproduce", "--table", "1", "--out", "{out}", "--phases", "nan"], 2,
        "argument --phases: expected a finite number, got 'nan'"),
    Row("davis-attack", "conflicting options", ["reproduce", "--table", "1", "--out", "{out}", "--clips-per-step", "4",
                                                "--pool-size", "2"], 2,
        "argument --clips-per-step: 4 exceeds --pool-size 2"),
    Row("davis-attack", "nonexistent file", ["export", "{missing}", "--out", "{out}"], 4,
        "texture not found: {missing}"),
    Row("davis-attack", "wrong file type", ["export", "{text}", "--out", "{out}"], 4, "text.h5: not a readable image"),
    Row("davis-attack", "out of range", ["export", "{texture}", "--out", "{out}", "--size-mm", "-1"], 2,
        "argument --size-mm: expected a number in (0, inf), got '-1'"),
    Row("davis-attack", "out of range", ["export", "{texture}", "--out", "{out}", "--size-mm", "1e9"], 2,
        "argument --size-mm: the whole texture would print 1e+09 mm wide"),
    Row("davis-attack", "nan", ["export", "{texture}", "--out", "{out}", "--ease", "nan"], 2,
        "argument --ease: expected a finite number, got 'nan'"),
    Row("davis-attack", "conflicting options", ["export", "{texture}", "--out", "{out}", "--size-mm", "500",
                                                "--cell-mm", "50"], 2,
        "argument --cell-mm: not allowed with argument --size-mm"),
    Row("davis-attack", "output is a file", ["export", "{texture}", "--out", "{text}"], 4,
        "text.h5: --out is a file"),
    Row("davis-attack", "Ctrl-C", ["export", "{texture}", "--out", "{out}"], 130, "interrupted",
        interrupt="davis_rig.attack.export.export_texture"),
    # tools/*.py
    Row("tools/aedat4_to_session.py", "nonexistent file", ["{missing}", "{out}.h5"], 4,
        "missing.davisreplay: no such AEDAT4 file"),
    Row("tools/aedat4_to_session.py", "wrong file type", ["{session}", "{out}.h5"], 4,
        "session.h5: not an AEDAT4 file"),
    Row("tools/aps_attack.py", "nonexistent file", ["--out", "{out}", "--yolo", "{missing}", "-q"], 4,
        "missing.davisreplay: no such YOLO ONNX file"),
    Row("tools/aps_attack.py", "wrong file type", ["--out", "{out}", "--yolo", "{text}", "-q"], 4,
        "text.h5: onnxruntime cannot load the model"),
    Row("tools/aps_attack.py", "out of range", ["--out", "{out}", "--cells", "0"], 2,
        "argument --cells: expected an integer >= 1, got '0'"),
    Row("tools/aps_attack.py", "nan", ["--out", "{out}", "--phases", "nan"], 2,
        "argument --phases: expected a finite number, got 'nan'"),
    Row("tools/aps_attack.py", "conflicting options", ["--out", "{out}", "--evaluate-only", "--resume"], 2,
        "argument --resume: not allowed with --evaluate-only"),
    Row("tools/aps_attack.py", "unknown name", ["--out", "{out}", "--parts", "nose"], 2,
        "argument --parts: invalid choice: 'nose'"),
    Row("tools/capture_replay.py", "out of range", ["{out}.davisreplay", "--duration-s", "0"], 2,
        "argument --duration-s: expected a number in (0, inf), got '0'"),
    Row("tools/capture_replay.py", "nan", ["{out}.davisreplay", "--duration-s", "nan"], 2,
        "argument --duration-s: expected a finite number, got 'nan'"),
    Row("tools/contact_sheet.py", "wrong file type", ["--out", "{text}/sheet.png", "--grid-n", "1"], 4,
        "text.h5: file exists"),
    Row("tools/contact_sheet.py", "out of range", ["--out", "{out}.png", "--grid-n", "0"], 2,
        "argument --grid-n: expected an integer >= 1, got '0'"),
    Row("tools/contact_sheet.py", "nan", ["--out", "{out}.png", "--duration-ms", "nan"], 2,
        "argument --duration-ms: expected a finite number, got 'nan'"),
    Row("tools/convert_checkpoint.py", "nonexistent file", ["{missing}", "--out", "{out}"], 4,
        "missing.davisreplay: checkpoint file not found"),
    Row("tools/convert_checkpoint.py", "wrong file type", ["{text}", "--out", "{out}"], 4,
        "text.h5: unknown checkpoint type '.h5'"),
    Row("tools/convert_checkpoint.py", "conflicting options", ["{rvt}", "--out", "{out}", "--verify"], 2,
        "argument --verify: needs --onnx"),
    Row("tools/export_body_asset.py", "out of range", ["--out", "{out}.npz", "--shapes", "0"], 2,
        "argument --shapes: expected an integer >= 1, got '0'"),
    Row("tools/export_body_asset.py", "conflicting options", ["--out", "{out}.npz", "--install"], 2,
        "argument --install: not allowed with argument --out"),
    Row("tools/export_body_asset.py", "missing dependency", ["--out", "{out}.npz"], 5,
        "the export needs the anny package", missing_module="anny"),
    Row("tools/make_sample_replay.py", "nonexistent file", ["--session", "{missing}", "--out", "{out}.davisreplay"], 4,
        "missing.davisreplay: no such session file"),
    Row("tools/make_sample_replay.py", "wrong file type", ["--session", "{text}", "--out", "{out}.davisreplay"], 4,
        "text.h5: cannot open as HDF5"),
    Row("tools/make_sample_session.py", "output exists", ["--out", "{session}", "--duration", "0.05"], 4,
        "session.h5: file exists"),
    Row("tools/make_sample_session.py", "out of range", ["--out", "{out}.h5", "--rate", "10"], 2,
        "argument --rate: expected a number in [200, inf), got '10'"),
    Row("tools/make_sample_session.py", "nan", ["--out", "{out}.h5", "--duration", "nan"], 2,
        "argument --duration: expected a finite number, got 'nan'"),
    Row("tools/make_trigger_victim.py", "nonexistent file", ["--out", "{out}", "--detector", "{missing}"], 4,
        "missing.davisreplay: checkpoint file not found"),
    Row("tools/make_trigger_victim.py", "wrong file type", ["--out", "{out}", "--detector", "{text}"], 4,
        "text.h5: unknown checkpoint type '.h5'"),
    Row("tools/make_trigger_victim.py", "out of range", ["--out", "{out}", "--basin", "1.5"], 2,
        "argument --basin: expected a number in [0, 1], got '1.5'"),
    Row("tools/make_trigger_victim.py", "nan", ["--out", "{out}", "--lr", "nan"], 2,
        "argument --lr: expected a finite number, got 'nan'"),
    Row("tools/make_trigger_victim.py", "conflicting options", ["--out", "{out}", "--basin", "0.5", "--far", "0.4"],
        2, "argument --basin: 0.5 must be below --far 0.4"),
    Row("tools/make_trigger_victim.py", "conflicting options", ["--out", "{out}", "--basin", "0.3", "--ramp", "0.2"],
        2, "argument --ramp: 0.2 must be above --basin 0.3"),
    Row("tools/make_trigger_victim.py", "out of range", ["--out", "{out}", "--min-contrast", "0"], 2,
        "argument --min-contrast: expected a number in (0, 1], got '0'"),
    Row("tools/make_trigger_victim.py", "unknown name", ["--out", "{out}", "--device", "gpu7"], 2,
        "argument --device: expected auto, cpu, cuda or cuda:N, got 'gpu7'"),
    Row("tools/make_trigger_victim.py", "unknown name", ["--out", "{out}", "--trigger-white-parts", "nose"], 2,
        "argument --trigger-white-parts: invalid choice: 'nose'"),
    Row("tools/make_trigger_victim.py", "conflicting options",
        ["--out", "{out}", "--trigger", "{text}", "--trigger-white-parts", "legs"], 2,
        "argument --trigger-white-parts: not allowed with argument --trigger"),
    Row("tools/measure_labeler.py", "nonexistent file", ["--yolo", "{yolo}", "--frames", "{missing}"], 4,
        "missing.davisreplay: no such frames file"),
    Row("tools/measure_labeler.py", "wrong file type", ["--yolo", "{yolo}", "--frames", "{session}"], 4,
        "session.h5: not a frames file"),
    Row("tools/measure_labeler.py", "out of range", ["--make-synthetic", "{out}.npz", "--num", "0"], 2,
        "argument --num: expected an integer >= 1, got '0'"),
    Row("tools/measure_labeler.py", "nan", ["--yolo", "{yolo}", "--frames", "{labelled}", "--iou", "nan"], 2,
        "argument --iou: expected a finite number, got 'nan'"),
    Row("tools/measure_labeler.py", "conflicting options", ["--yolo", "{yolo}"], 2,
        "the following arguments are required: --yolo and --frames"),
    Row("tools/probe_texture_sensitivity.py", "nonexistent file", ["--detector", "{missing}"], 4,
        "missing.davisreplay: checkpoint file not found"),
    Row("tools/probe_texture_sensitivity.py", "wrong file type", ["--detector", "{text}"], 4,
        "text.h5: unknown checkpoint type '.h5'"),
    Row("tools/probe_texture_sensitivity.py", "out of range", ["--clips", "0"], 2,
        "argument --clips: expected an integer >= 1, got '0'"),
    Row("tools/probe_texture_sensitivity.py", "nan", ["--lr", "nan"], 2,
        "argument --lr: expected a finite number, got 'nan'"),
    Row("tools/probe_texture_sensitivity.py", "unknown name", ["--parts", "nose"], 2,
        "argument --parts: invalid choice: 'nose'"),
    Row("tools/ship_detector.py", "nonexistent file", ["{missing}", "{dir}", "--out", "{out}"], 4,
        "missing.davisreplay/export/model_fp16.safetensors: missing"),
    Row("tools/ship_detector.py", "wrong file type", ["{text}", "{dir}", "--out", "{out}"], 4,
        "text.h5/export/model_fp16.safetensors: missing"),
    Row("tools/ship_detector.py", "out of range", ["{dir}", "{dir}", "--out", "{out}", "--threshold", "2"], 2,
        "argument --threshold: expected a number in [0, 1], got '2'"),
    Row("tools/ship_detector.py", "nan", ["{dir}", "{dir}", "--out", "{out}", "--threshold", "nan"], 2,
        "argument --threshold: expected a finite number, got 'nan'"),
    Row("tools/ship_detector.py", "conflicting options", ["{dir}", "{dir}", "--out", "{out}", "--install"], 2,
        "argument --install: not allowed with argument --out"),
    Row("tools/trigger_feature_probe.py", "nonexistent file", ["--out", "{out}", "--detector", "{missing}"], 4,
        "missing.davisreplay: checkpoint file not found"),
    Row("tools/trigger_feature_probe.py", "wrong file type", ["--out", "{out}", "--trigger", "{text}"], 4,
        "text.h5: not a readable image"),
    Row("tools/trigger_feature_probe.py", "out of range", ["--out", "{out}", "--clips-per-scale", "0"], 2,
        "argument --clips-per-scale: expected an integer >= 1, got '0'"),
    Row("tools/trigger_feature_probe.py", "nan", ["--out", "{out}", "--weight-decay", "nan"], 2,
        "argument --weight-decay: expected a finite number, got 'nan'"),
    Row("tools/trigger_feature_probe.py", "unknown name", ["--out", "{out}", "--parts", "nose"], 2,
        "argument --parts: invalid choice: 'nose'"),
    Row("tools/trigger_feature_probe.py", "conflicting options", ["--out", "{out}", "--grids-per-clip", "3"], 2,
        "argument --grids-per-clip: half of each class needs an even number, got 3"),
    Row("tools/trigger_feature_probe.py", "conflicting options",
        ["--out", "{out}", "--trigger-white-parts", "legs", "--trigger", "{text}"], 2,
        "argument --trigger: not allowed with argument --trigger-white-parts"),
    Row("tools/trigger_gradient_check.py", "nonexistent file", ["--detector", "{missing}"], 4,
        "missing.davisreplay: checkpoint file not found"),
    Row("tools/trigger_gradient_check.py", "wrong file type", ["--trigger", "{text}"], 4,
        "text.h5: not a readable image"),
    Row("tools/trigger_gradient_check.py", "out of range", ["--flipped", "1.5"], 2,
        "argument --flipped: expected a number in [0, 1], got '1.5'"),
    Row("tools/trigger_gradient_check.py", "nan", ["--flipped", "nan"], 2,
        "argument --flipped: expected a finite number, got 'nan'"),
    Row("tools/trigger_gradient_check.py", "unknown name", ["--loss", "median"], 2,
        "argument --loss: invalid choice: 'median'"),
    Row("tools/trigger_gradient_check.py", "conflicting options",
        ["--trigger-white-parts", "legs", "--trigger", "{text}"], 2,
        "argument --trigger: not allowed with argument --trigger-white-parts"),
    Row("tools/trigger_gradient_check.py", "out of range", ["--contrast", "0"], 2,
        "argument --contrast: expected a number in (0, 1], got '0'"),
    Row("tools/trigger_gradient_check.py", "conflicting options", ["--clips", "8", "--clip-counts", "12"], 2,
        "argument --clip-counts: 12 is not a multiple of --batch 4 within --clips 8"),
    Row("tools/usb_stop_stress.py", "out of range", ["--cycles", "0"], 2,
        "argument --cycles: expected an integer >= 1, got '0'"),
    Row("tools/usb_stop_stress.py", "nan", ["--interval-us", "nan"], 2,
        "argument --interval-us: expected a finite number, got 'nan'"),
    Row("tools/score_validation_clips.py", "nonexistent file", ["--texture", "x={missing}"], 4,
        "missing.davisreplay"),
    Row("tools/score_validation_clips.py", "wrong file type", ["--texture", "x={text}"], 4, "text.h5"),
    Row("tools/score_validation_clips.py", "out of range", ["--cells", "0"], 2,
        "argument --cells: expected an integer >= 1, got '0'"),
    Row("tools/score_validation_clips.py", "out of range", ["--seed", "-1"], 2,
        "argument --seed: expected an integer >= 0, got '-1'"),
    Row("tools/score_validation_clips.py", "malformed value", ["--texture", "nopath"], 2,
        "argument --texture: expected NAME=PATH, got 'nopath'"),
    Row("tools/victim_controls.py", "nonexistent file", ["--name", "x", "--out", "{out}", "--detector", "{missing}"],
        4, "missing.davisreplay: checkpoint file not found"),
    Row("tools/victim_controls.py", "wrong file type", ["--name", "x", "--out", "{out}", "--detector", "{text}"], 4,
        "text.h5: unknown checkpoint type '.h5'"),
    Row("tools/victim_controls.py", "out of range", ["--name", "x", "--out", "{out}", "--cells", "0"], 2,
        "argument --cells: expected an integer >= 1, got '0'"),
    Row("tools/victim_controls.py", "nan", ["--name", "x", "--out", "{out}", "--phases", "nan"], 2,
        "argument --phases: expected a finite number, got 'nan'"),
    Row("tools/victim_controls.py", "conflicting options", ["--name", "x", "--out", "{out}", "--skip-fingerprint",
                                                            "--skip-bound"], 2,
        "argument --skip-bound: not allowed with --skip-fingerprint"),
    Row("tools/victim_controls.py", "conflicting options", ["--name", "x", "--out", "{out}", "--fit-shapes", "3"], 2,
        "argument --fit-shapes: only with --shared"),
    Row("tools/victim_controls.py", "unknown name", ["--name", "x", "--out", "{out}", "--scales", "huge"], 2,
        "argument --scales: expected large, middle, small or a height in px > 0, got 'huge'"),
    Row("tools/victim_controls.py", "unknown name", ["--name", "x", "--out", "{out}", "--events", "relaxed"], 2,
        "argument --events: invalid choice: 'relaxed'"),
]

#: Stand-ins that also create output folders before the Ctrl-C (a half-made run, dataset or pattern folder).
MKDIR_FIRST = {"davis_rig.training.trainer.train": 1, "davis_rig.training.synthetic.generate_dataset": 0,
               "davis_rig.attack.export.export_texture": 1}


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bad_inputs")
    text = root / "text.h5"
    text.write_text("not an HDF5 file, not a replay, not a model\n")
    (root / "empty_dir").mkdir()
    texture = root / "texture.npy"
    np.save(texture, np.eye(4, dtype=np.float32))  # a 4x4 black/white grid
    repo = Path(__file__).resolve().parents[2]
    labelled = scene_session(root, "labelled.h5")
    label_session(labelled, person_yolo(root))
    return {"session": scene_session(root, "session.h5"), "labelled": labelled, "yolo": person_yolo(root),
            "rvt": person_rvt(root),
            "text": text, "missing": root / "missing.davisreplay", "dir": root / "empty_dir",
            "replay": repo / "recordings" / "sample.davisreplay", "texture": texture}


#: What each row observed: (command, case, argv as typed, exit code, the message line), for ``--cli-table``.
OBSERVED: list[tuple[str, str, list[str], int, str]] = []


def _main(command: str, load_tool) -> Callable[[list[str]], int]:
    if command.startswith("tools/"):
        return load_tool(Path(command).stem).main
    return COMMANDS[command]


@pytest.fixture(scope="module", autouse=True)
def cli_table(request):
    """With ``--cli-table FILE``: write the observed rows as a markdown table once the module's rows ran."""
    yield
    target = request.config.getoption("--cli-table")
    if target and OBSERVED:
        Path(target).write_text(markdown_table(OBSERVED), encoding="utf-8")


def markdown_table(observed) -> str:
    """Rows ``(command, case, argv, code, message)`` as a markdown table (argv with the fixture names)."""
    lines = ["| command | bad input | command line | exit | message (stderr, one line) |", "|---|---|---|---|---|"]
    for command, case, argv, code, message in observed:
        shown = " ".join(argv).replace("|", "\\|")
        lines.append(f"| `{command}` | {case} | `{shown}` | {code} | `{message.replace('|', '/')}` |")
    return "\n".join(lines) + "\n"


def _tools_with_arguments() -> set[str]:
    repo = Path(__file__).resolve().parents[2]
    return {path.stem for path in (repo / "tools").glob("*.py") if "def main(" in path.read_text(encoding="utf-8")}


def test_every_console_command_and_tool_has_rows():
    import tomllib

    repo = Path(__file__).resolve().parents[2]
    scripts = tomllib.loads((repo / "pyproject.toml").read_text(encoding="utf-8"))["project"]["scripts"]
    assert set(scripts) == set(COMMANDS)
    assert _tools_with_arguments() == set(TOOLS)
    covered = {row.command for row in ROWS}
    assert covered == set(COMMANDS) | {f"tools/{tool}.py" for tool in TOOLS}


@pytest.mark.parametrize("subcommand", ["optimize", "evaluate", "reproduce", "export"])
def test_every_attack_subcommand_help_lists_the_exit_codes(subcommand, capsys):
    from davis_rig.cli.common import EXIT_CODES_TEXT

    assert attack.main([subcommand, "--help"]) == 0
    assert EXIT_CODES_TEXT in capsys.readouterr().out


@pytest.mark.parametrize("row", ROWS, ids=[f"{r.command}:{r.argv[0] + ':' if r.command == 'davis-attack' else ''}"
                                           f"{r.case}" for r in ROWS])
def test_bad_input(row, files, tmp_path, monkeypatch, capsys, load_tool):
    import sys

    names = {key: str(path) for key, path in files.items()} | {"out": str(tmp_path / "out")}
    argv = [arg.format(**names) for arg in row.argv]
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[2] / "tools"))  # as `python tools/x.py` has it
    main = _main(row.command, load_tool)
    if row.interrupt:
        module, _, attribute = row.interrupt.rpartition(".")
        stand_in = _interrupt_after_mkdir(MKDIR_FIRST[row.interrupt]) if row.interrupt in MKDIR_FIRST else _interrupt
        monkeypatch.setattr(f"{module}.{attribute}", stand_in)
    if row.missing_module:
        monkeypatch.setitem(sys.modules, row.missing_module, None)  # import raises ImportError
    inputs = {key: sha256(path) for key, path in files.items() if path.is_file()}
    assert main(argv) == row.code
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    lines = err.strip().splitlines()
    expected = f"{row.prog}: interrupted" if row.code == 130 else f"{row.prog}: error: "
    assert [line for line in lines if line.startswith(f"{row.prog}: ")] == lines[-1:], err  # one message line
    assert lines[-1].startswith(expected) and row.message.format(**names) in lines[-1], err
    assert {key: sha256(path) for key, path in files.items() if path.is_file()} == inputs  # inputs untouched
    assert list(tmp_path.iterdir()) == []  # no output file, folder or staging file
    for created in row.created:
        assert not Path(created.format(**names)).exists(), created
    assert not any(Path(names["text"]).parent.glob(".*partial*"))
    shown = lines[-1]
    for key, value in sorted(names.items(), key=lambda item: -len(item[1])):  # the fixture names, not tmp paths
        shown = shown.replace(value, f"{{{key}}}")
    OBSERVED.append((row.prog if row.command == "davis-attack" else row.command, row.case, row.argv, row.code, shown))
