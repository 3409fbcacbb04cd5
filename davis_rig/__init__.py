"""davis_rig: DAVIS346 capture, RVT evaluation and physical adversarial textures for event-based detectors.

Layout (imports run one way: a package imports only the packages listed before it; ``tests/test_import_layers.py``
holds this order as data and fails on an import against it):

- ``errors``, ``types``, ``stop``: the exception tree, the canonical event dtype and sensor geometry; stop
  requests (Ctrl-C as a flag that long loops poll between steps).
- ``protocol``: bytes <-> events, pure (USB word decoder/encoder, config and bias encoding).
- ``usb``: the only package that imports ``usb`` (pyusb transport, virtual DAVIS346 backend).
- ``device``: the camera (configure, start/stop, reader thread).
- ``session``: the session.h5 file (schema, writer, reader, recovery, imports).
- ``events``: event kernels (crop, RVT histograms, the exact simulator, the differentiable V2E).
- ``models``: detectors (RVT in PyTorch, ONNX export, onnxruntime runner).
- ``labelers``, ``metrics``: YOLO ground truth of APS frames; AP and SeqASR.
- ``evaluation``: the physical evaluation of a recording and its report.
- ``scene``: the digital scene (body, motion, camera, rasterizer, textures, backgrounds, APS synthesis).
- ``training``: synthetic data (datasets, synthetic session files), the RVT training recipe.
- ``attack``: the digital adversarial texture optimizer and its evaluation.
- ``attack_aps``, ``controls``: the texture pipeline against the APS labeler's YOLO (the real-data control); a
  victim's fingerprint, free-appearance bound and selective planted blind spot.
- ``interop``, ``viewer``: a session in the formats other tools read; the session viewer.
- ``cli``: thin command-line front ends; it may import anything, nothing imports it.
"""

__version__ = "0.1.0"
