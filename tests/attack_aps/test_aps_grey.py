"""The differentiable APS grey level equals the noiseless ADC as the labeler reads it."""

from __future__ import annotations

import numpy as np
import torch

from davis_rig.attack_aps.attack import aps_grey
from davis_rig.labelers.yolo import to_gray_u8
from davis_rig.scene.aps import ApsConfig, to_adc


def test_aps_grey_is_the_noiseless_adc_read_as_8_bit():
    intensity = np.linspace(0.0, 1.2, 61, dtype=np.float32).reshape(1, -1)
    config = ApsConfig(shot_noise=False, read_noise_dn=0.0)
    labeler = to_gray_u8(to_adc(intensity, config)).astype(np.float64)
    ours = aps_grey(torch.from_numpy(intensity), config).numpy() * 255.0
    assert np.abs(ours - labeler).max() <= 1.0  # the ADC rounds to DN, the labeler drops 2 bits
    x = torch.tensor([0.5], requires_grad=True)
    aps_grey(x).sum().backward()
    assert float(x.grad) > 0
