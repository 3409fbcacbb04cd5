"""Helper modules shared by the tests (import them by name, e.g. ``from tests.helpers.eval_data import ...``).

- :mod:`~tests.helpers.camera_reads`: read a camera over the virtual DAVIS346 until drained (tests/usb, tests/device);
- :mod:`~tests.helpers.davis346_vectors`: the committed DAVIS346 test vectors and the full decode-vs-vector
  comparison (tests/protocol, tests/device);
- :mod:`~tests.helpers.eval_data`: tiny ONNX graphs with known outputs, sessions recorded through the virtual
  camera (evaluation, labelers, cli);
- :mod:`~tests.helpers.libusb_emu`: an emulated libusb-1.0 below pyusb playing VirtualDavis346 models, and the
  ``usb_backend`` fixture (tests/usb, tests/device, tests/session);
- :mod:`~tests.helpers.mocap_files`: tiny synthetic AMASS .npz / CMU BVH files (tests/scene/mocap, tests/attack);
- :mod:`~tests.helpers.session_data`: synthetic events, frames and fake cameras of the session tests.
"""
