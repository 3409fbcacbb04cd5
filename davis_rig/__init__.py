"""davis_rig: DAVIS346 capture, RVT evaluation and physical adversarial textures for event-based detectors.

Layout (imports run one way, top to bottom):

- ``errors``, ``types``: the exception tree, the canonical event dtype and sensor geometry.
- ``protocol``: bytes <-> events, pure (USB word decoder/encoder, config and bias encoding).
- ``usb``: the only package that imports ``usb`` (pyusb transport, virtual DAVIS346 backend).
- ``device``: the camera (configure, start/stop, reader thread).
- ``session``: the session.h5 file (schema, writer, reader, recovery, imports).
- ``events``: event kernels (crop, RVT histograms).
- ``models``: detectors (RVT in PyTorch, ONNX export, onnxruntime runner).
- ``cli``: thin command-line front ends; nothing imports it.
"""

__version__ = "0.1.0"
