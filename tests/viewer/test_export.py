"""``export_video``: a long GIF export does not hold every rendered window in memory."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

#: Exports a fake view of ``windows`` noise windows (260x696 RGB, no two alike; 64 colours, as the viewer's layers
#: have few, which keeps Pillow's palette quantization quick) to a GIF and prints the growth of the peak resident
#: memory during the export, KiB.
_EXPORT = textwrap.dedent("""
    import resource, sys
    import numpy as np
    from davis_rig.viewer.export import export_video

    COLOURS = np.random.default_rng(0).integers(0, 256, (64, 3), dtype=np.uint8)

    class View:
        num_windows, window_us, detections = int(sys.argv[2]), 50_000, None

        def render(self, k, layers, threshold, caption):
            return COLOURS[np.random.default_rng(k).integers(0, len(COLOURS), (260, 696))]

    view = View()
    from PIL import Image  # imported before the baseline
    Image.fromarray(view.render(0, None, None, True)).save(sys.argv[1] + ".warm.gif")
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    export_video(view, sys.argv[1])
    print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before)
""")


def test_a_gif_export_keeps_one_rendered_window_at_a_time(tmp_path):
    pytest.importorskip("PIL", reason="the GIF export needs the report extra (Pillow)")
    windows = 120
    run = subprocess.run([sys.executable, "-c", _EXPORT, str(tmp_path / "v.gif"), str(windows)], capture_output=True,
                         text=True, timeout=300, check=True)
    growth_kib = int(run.stdout)
    rgb_kib = 260 * 696 * 4 / 1024  # one rendered window as a Pillow RGB image (4 bytes per pixel)
    # Pillow keeps its palette copy of each frame (1 byte per pixel) until the file is written; the rendered RGB
    # windows (4 bytes per pixel) are not all kept as well.
    assert growth_kib < windows * rgb_kib / 2, (growth_kib, windows * rgb_kib)
