"""Procedural and image backgrounds."""

import numpy as np
import pytest

from davis_rig.errors import FormatError
from davis_rig.scene import background as bg


def test_procedural_backgrounds_shape_and_range():
    rng = np.random.default_rng(0)
    images = [
        bg.uniform((24, 30), 0.3),
        bg.noise((24, 30), rng),
        bg.stripes((24, 30), period_px=8),
        bg.checker((24, 30), cell_px=6),
        bg.gradient((24, 30)),
        bg.rectangles((24, 30), rng),
    ] + [bg.random_background((24, 30), rng) for _ in range(20)]
    for image in images:
        assert image.shape == (24, 30) and image.dtype == np.float32
        assert image.min() >= 0.0 and image.max() <= 1.0


def test_checker_and_stripes_values():
    c = bg.checker((4, 4), cell_px=2, low=0.0, high=1.0)
    assert c.tolist() == [[0, 0, 1, 1], [0, 0, 1, 1], [1, 1, 0, 0], [1, 1, 0, 0]]
    s = bg.stripes((2, 8), period_px=4, low=0.0, high=1.0, soft=False)
    assert s[0].tolist() == [0, 0, 1, 1, 0, 0, 1, 1]
    g = bg.gradient((5, 3), low=0.0, high=1.0)
    assert g[0, 0] == 0.0 and g[-1, 0] == 1.0 and np.all(np.diff(g[:, 1]) > 0)


def test_from_image(tmp_path):
    import cv2

    image = np.zeros((20, 40), np.uint8)
    image[:, 20:] = 255
    path = tmp_path / "bg.png"
    cv2.imwrite(str(path), image)
    out = bg.from_image(path, (10, 10))  # scaled to cover (10 x 20), centre-cropped
    assert out.shape == (10, 10)
    assert out[:, 0].max() < 0.05 and out[:, -1].min() > 0.95
    with pytest.raises(FileNotFoundError):
        bg.from_image(tmp_path / "missing.png", (10, 10))
    (tmp_path / "junk.png").write_bytes(b"not an image")
    with pytest.raises(FormatError):
        bg.from_image(tmp_path / "junk.png", (10, 10))
