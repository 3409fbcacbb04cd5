"""The capture path (protocol/usb/device) must not import torch (house rule: capture runs without the torch extra)."""

import subprocess
import sys


def test_capture_path_does_not_import_torch():
    code = (
        "import sys\n"
        "import davis_rig.device.camera, davis_rig.usb.virtual, davis_rig.usb.replay, davis_rig.usb.sources\n"
        "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.') or m == 'onnx')\n"
        "print(','.join(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert out == ""
