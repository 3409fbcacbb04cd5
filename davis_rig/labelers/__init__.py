"""Ground-truth labelers for physical recordings: ``yolo`` (YOLO ONNX detector, onnxruntime, no torch) and
``session_labels`` (label a session's APS frames, store ``/labels``)."""
