"""Every command × {nonexistent file, wrong file type, out-of-range, NaN, conflicting options, Ctrl-C}.

Each row: the documented exit code, one ``<command>: error: ...`` line (or ``<command>: interrupted``) and no
traceback on stderr, and nothing half-written: the inputs unchanged and no output file or empty output folder
left. Ctrl-C is a ``KeyboardInterrupt`` raised inside the command's API call (for ``davis-record`` a Ctrl-C
while recording is a clean stop instead: tests/session/test_capture_end_to_end.py sends a real SIGINT).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import pytest

from davis_rig.cli import eval as eval_cli
from davis_rig.cli import eval_dataset, label, make_dataset, record, train
from davis_rig.labelers.session_labels import label_session

from tests.helpers.eval_data import person_rvt, person_yolo, scene_session, sha256

COMMANDS = {"davis-record": record.main, "davis-label": label.main, "davis-eval": eval_cli.main,
            "davis-eval-dataset": eval_dataset.main, "davis-train": train.main,
            "davis-make-dataset": make_dataset.main}


@dataclass
class Row:
    """One bad input: ``argv`` gets the files of :func:`files` by name (``{session}``, ``{out}``, ...)."""

    command: str
    case: str
    argv: list[str]
    code: int
    message: str
    interrupt: str | None = None  # "module.attribute" replaced by a function raising KeyboardInterrupt
    created: list[str] = field(default_factory=list)  # paths that must not exist afterwards


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
        "missing.davisreplay", created=["{out}.h5"]),
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
        "Not a directory"),
    Row("davis-make-dataset", "wrong file type", ["--out", "{text}", "--sequences", "3", "-q"], 4, "text.h5"),
    Row("davis-make-dataset", "out of range", ["--out", "{out}", "--sequences", "0"], 2,
        "argument --sequences: expected an integer >= 1, got '0'", created=["{out}"]),
    Row("davis-make-dataset", "nan", ["--out", "{out}", "--sequences", "3", "--test-scale-probability", "nan"], 2,
        "argument --test-scale-probability: expected a finite number, got 'nan'", created=["{out}"]),
    Row("davis-make-dataset", "conflicting options", ["{out}", "--out", "{out}", "--sequences", "3"], 2,
        "argument --out: not allowed with a positional OUT_DIR", created=["{out}"]),
    Row("davis-make-dataset", "Ctrl-C", ["--out", "{out}", "--sequences", "3", "-q"], 130, "interrupted",
        interrupt="davis_rig.training.synthetic.generate_dataset", created=["{out}"]),
]

#: Stand-ins that also create output folders before the Ctrl-C (a half-made run or dataset folder).
MKDIR_FIRST = {"davis_rig.training.trainer.train": 1, "davis_rig.training.synthetic.generate_dataset": 0}


@pytest.fixture(scope="module")
def files(tmp_path_factory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("bad_inputs")
    text = root / "text.h5"
    text.write_text("not an HDF5 file, not a replay, not a model\n")
    (root / "empty_dir").mkdir()
    repo = Path(__file__).resolve().parents[2]
    labelled = scene_session(root, "labelled.h5")
    label_session(labelled, person_yolo(root))
    return {"session": scene_session(root, "session.h5"), "labelled": labelled, "yolo": person_yolo(root),
            "rvt": person_rvt(root),
            "text": text, "missing": root / "missing.davisreplay", "dir": root / "empty_dir",
            "replay": repo / "recordings" / "sample.davisreplay"}


@pytest.mark.parametrize("row", ROWS, ids=[f"{r.command}:{r.case}" for r in ROWS])
def test_bad_input(row, files, tmp_path, monkeypatch, capsys):
    names = {key: str(path) for key, path in files.items()} | {"out": str(tmp_path / "out")}
    argv = [arg.format(**names) for arg in row.argv]
    if row.interrupt:
        module, _, attribute = row.interrupt.rpartition(".")
        stand_in = _interrupt_after_mkdir(MKDIR_FIRST[row.interrupt]) if row.interrupt in MKDIR_FIRST else _interrupt
        monkeypatch.setattr(f"{module}.{attribute}", stand_in)
    inputs = {key: sha256(path) for key, path in files.items() if path.is_file()}
    assert COMMANDS[row.command](argv) == row.code
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    last = err.strip().splitlines()[-1]
    expected = f"{row.command}: interrupted" if row.code == 130 else f"{row.command}: error: "
    assert last.startswith(expected) and row.message in last, err
    assert {key: sha256(path) for key, path in files.items() if path.is_file()} == inputs  # inputs untouched
    for created in row.created:
        assert not Path(created.format(**names)).exists(), created
    assert not any((tmp_path / "out").parent.glob(".*partial*"))  # no staging file or folder
