"""The capture path (protocol/usb/device) must not import torch (house rule: capture runs without the torch extra)."""


def test_capture_path_does_not_import_torch(fresh_python):
    code = (
        "import sys\n"
        "import davis_rig.device.camera, davis_rig.usb.virtual, davis_rig.usb.replay, davis_rig.usb.sources\n"
        "bad = sorted(m for m in sys.modules if m == 'torch' or m.startswith('torch.') or m == 'onnx')\n"
        "print(','.join(bad))\n"
    )
    assert fresh_python(code) == ""
