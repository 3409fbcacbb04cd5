"""The bundled replay (the README's main capture job) re-records into exactly the bundled sample session."""

import subprocess
import sys
from pathlib import Path

import numpy as np

from davis_rig.session.reader import SessionReader

RECORDINGS = Path(__file__).resolve().parents[2] / "recordings"


def test_davis_record_on_the_bundled_replay_reproduces_the_sample_session(tmp_path):
    out = tmp_path / "session.h5"
    done = subprocess.run(
        [sys.executable, "-m", "davis_rig.cli.record", "--quiet", "--fake", str(RECORDINGS / "sample.davisreplay"),
         "--out", str(out)],
        capture_output=True, text=True, timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "dropped transfers: 0" in done.stderr + done.stdout
    with SessionReader(RECORDINGS / "sample.h5") as expected, SessionReader(out) as recorded:
        assert recorded.complete
        np.testing.assert_array_equal(recorded.events(), expected.events())
        assert len(recorded.frames) == len(expected.frames) == 15
        for i in range(len(expected.frames)):
            a, b = expected.frames[i], recorded.frames[i]
            np.testing.assert_array_equal(b.pixels, a.pixels)
            assert (b.t_start_exposure_us, b.t_end_exposure_us) == (a.t_start_exposure_us, a.t_end_exposure_us)
        assert not (tmp_path / "session.h5.journal").exists()
