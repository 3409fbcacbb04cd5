"""Tests of ``benchmarks/run_all.py`` (the one command that runs every benchmark script)."""

from __future__ import annotations

import re
from pathlib import Path

_DIR = Path(__file__).resolve().parents[2] / "benchmarks"


def test_every_script_is_listed_once_and_in_order(run_all):
    on_disk = {p.stem for p in _DIR.glob("*.py") if not p.stem.startswith("_") and p.stem != "run_all"}
    names = run_all.scripts()
    assert sorted(names) == sorted(on_disk) and len(names) == len(set(names))
    assert set(run_all.ORDER) == on_disk, "a new benchmark script needs its place in ORDER"


def test_quick_arguments_are_options_the_scripts_accept(run_all):
    for name, args in run_all.QUICK_ARGS.items():
        source = (_DIR / f"{name}.py").read_text(encoding="utf-8")
        accepted = set(re.findall(r'add_argument\(\s*"(--[a-z0-9-]+)"', source))
        flags = {a for a in args if a.startswith("--")}
        assert flags <= accepted, f"{name}.py does not accept {sorted(flags - accepted)}"


def test_report_keeps_each_scripts_output_and_counts_failures(run_all, tmp_path, monkeypatch):
    outputs = {"decode": (0, 0.5, "decode figures\n"), "io": (3, 0.2, "io broke\n")}
    monkeypatch.setattr(run_all, "run_one", lambda name, extra: outputs[name])
    report = tmp_path / "report.txt"
    assert run_all.main(["--only", "decode", "io", "--out", str(report)]) == 1
    text = report.read_text()
    assert "== python benchmarks/decode.py\ndecode figures\n-- exit 0" in text
    assert "== python benchmarks/io.py\nio broke\n-- exit 3" in text
