"""tools/contact_sheet.py writes a PNG grid of rendered scenes (short clips, one sample per pixel)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("torch")
cv2 = pytest.importorskip("cv2")


def test_contact_sheet_png(tmp_path, capsys, load_tool):
    out = tmp_path / "sheet.png"
    tool = load_tool("contact_sheet")
    assert tool.main(["--out", str(out), "--supersample", "1", "--duration-ms", "10", "--grid-n", "4"]) == 0
    sheet = cv2.imread(str(out))
    assert sheet is not None
    scenes = 5
    assert sheet.shape == (scenes * (18 + 242), 5 * 306, 3)  # title strip + 5 tiles of 304 x 240 (+1 px border)
    # every frame tile shows a person (pixels differ from the tile's background) and a green box
    first = sheet[19:259, 1:305]
    assert (np.abs(first.astype(int) - first[5, 5].astype(int)).sum(-1) > 30).sum() > 500
    assert ((first[..., 1] > 200) & (first[..., 0] < 50) & (first[..., 2] < 50)).any()
    assert "wrote" in capsys.readouterr().out
