"""A real Ctrl-C (SIGINT) to each long-running command while it works: exit 130, one ``<command>: interrupted``
line, no traceback, and the output state each command documents.

davis-label, davis-eval, davis-eval-dataset, davis-export and davis-view --export leave nothing (the input
unchanged, no output, no staging file); davis-make-dataset keeps the finished sequences (a rerun continues);
davis-train finishes the step in progress and writes its checkpoint (``--resume`` continues). Elsewhere:
davis-record stops cleanly (exit 0, a complete file: tests/session/test_capture_end_to_end.py), the davis-view server stops (exit 0:
tests/viewer/test_cli.py), davis-attack optimize writes a checkpoint and exits 130
(tests/cli/test_attack_commands.py) and davis-attack search keeps its finished generations and exits 130
(tests/cli/test_attack_search.py). See :mod:`tests.helpers.interrupt` for how the commands are caught mid-work.
"""

from __future__ import annotations

import json

import pytest

from davis_rig.labelers.session_labels import label_session

from tests.helpers.eval_data import person_rvt, person_yolo, scene_session, sha256
from tests.helpers.interrupt import interrupt_while_working


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("ctrl_c")
    labelled = scene_session(root, "labelled.h5")
    label_session(labelled, person_yolo(root))
    return {"session": scene_session(root, "session.h5"), "labelled": labelled, "yolo": person_yolo(root),
            "rvt": person_rvt(root)}


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    """A 0.15 s synthetic dataset: one train, one val and one test sequence."""
    pytest.importorskip("torch")
    from davis_rig.training.synthetic import generate_dataset

    data = tmp_path_factory.mktemp("ctrl_c_data") / "synth"
    generate_dataset(data, {"train": 1, "val": 1, "test": 1}, duration_s=0.15, seed=3, compression="gzip",
                     threads=1)
    return data


def _assert_interrupted(result, prog: str) -> None:
    assert result.returncode == 130, result.stderr
    assert "Traceback" not in result.stderr, result.stderr
    assert result.last_line == f"{prog}: interrupted", result.stderr


def _nothing_but(folder, names) -> None:
    """Only ``names`` in ``folder`` (no output file, no staging file)."""
    assert sorted(p.name for p in folder.iterdir()) == sorted(names)


def test_label_leaves_the_session_unchanged(inputs, tmp_path):
    session = tmp_path / "s.h5"
    session.write_bytes(inputs["session"].read_bytes())
    before = sha256(session)
    result = interrupt_while_working("davis_rig.cli.label:main", [str(session), "--yolo", str(inputs["yolo"]), "-q"],
                                     "davis_rig.labelers.yolo:YoloOnnxDetector.detect", tmp_path)
    _assert_interrupted(result, "davis-label")
    assert sha256(session) == before
    _nothing_but(tmp_path, ["s.h5", ".working"])


def test_eval_leaves_no_report(inputs, tmp_path):
    result = interrupt_while_working(
        "davis_rig.cli.eval:main", [str(inputs["labelled"]), "--detector", str(inputs["rvt"]), "--out",
                                    str(tmp_path / "report"), "--threads", "1", "-q"],
        "davis_rig.models.rvt.ort_runner:RVTOnnxRunner.prepare_histogram", tmp_path)
    _assert_interrupted(result, "davis-eval")
    _nothing_but(tmp_path, [".working"])


def test_export_leaves_no_file(inputs, tmp_path):
    result = interrupt_while_working(
        "davis_rig.cli.export:main", [str(inputs["labelled"]), "--to", "npz", "--out", str(tmp_path / "x.npz"), "-q"],
        "davis_rig.interop.source:ExportSource.event_chunks", tmp_path)
    _assert_interrupted(result, "davis-export")
    _nothing_but(tmp_path, [".working"])


def test_view_export_leaves_no_video(inputs, tmp_path):
    pytest.importorskip("PIL")
    result = interrupt_while_working(
        "davis_rig.cli.view:main", [str(inputs["session"]), "--no-detector", "--export", str(tmp_path / "v.gif"),
                                    "-q"],
        "davis_rig.viewer.recording:RecordingView.render", tmp_path)
    _assert_interrupted(result, "davis-view")
    _nothing_but(tmp_path, [".working"])


@pytest.mark.slow  # the dataset fixture renders three sequences: 10-20 s on a shared CPU
def test_eval_dataset_leaves_no_json(dataset, tmp_path):
    result = interrupt_while_working(
        "davis_rig.cli.eval_dataset:main", [str(dataset), "--split", "test", "--out", str(tmp_path / "scores.json"),
                                            "--threads", "1", "-q"],
        "davis_rig.training.dataset:SequenceData.histograms", tmp_path)
    _assert_interrupted(result, "davis-eval-dataset")
    _nothing_but(tmp_path, [".working"])


def test_make_dataset_keeps_the_finished_sequences(tmp_path):
    out = tmp_path / "data"
    result = interrupt_while_working(
        "davis_rig.cli.make_dataset:main", ["--out", str(out), "--sequences", "3", "--seconds", "0.15",
                                            "--threads", "1", "--compression", "gzip", "-q"],
        "davis_rig.training.dataset:DatasetWriter.add_sequence", tmp_path)
    _assert_interrupted(result, "davis-make-dataset")
    finished = [meta.parent for meta in out.rglob("meta.json")]
    assert len(finished) == 1  # the sequence written before the Ctrl-C, complete: a rerun skips it
    assert json.loads((finished[0] / "meta.json").read_text())["name"] == finished[0].name
    assert not any(out.rglob("*.partial*"))


@pytest.mark.slow  # the dataset fixture, then torch and the model load in the subprocess: > 10 s
def test_train_finishes_its_step_and_writes_its_checkpoint(dataset, tmp_path):
    torch = pytest.importorskip("torch")
    run = tmp_path / "run"
    result = interrupt_while_working(  # no periodic checkpoint before step 1000: the Ctrl-C writes the one there is
        "davis_rig.cli.train:main", [str(dataset), "--out", str(run), "--preset", "mini", "--steps", "100",
                                     "--batch", "2", "--seq-len", "2", "--val-every", "0", "--log-every", "1",
                                     "--device", "cpu", "--threads", "1", "-q"],
        "davis_rig.training.trainer:Trainer.train_step", tmp_path, after_items=2)
    _assert_interrupted(result, "davis-train")
    step = torch.load(run / "checkpoints" / "last.pt", map_location="cpu", weights_only=False)["step"]
    logged = [json.loads(line)["step"] for line in (run / "log.jsonl").read_text().splitlines()]
    assert 2 <= step < 100 and logged[-1] == step  # the step in progress finished: --resume continues after it
    assert f"checkpoint of step {step} written" in result.stderr and "--resume" in result.stderr
    assert not (run / "export").exists()
