"""Physical evaluation of recordings (the paper's Table 3): ``physical`` (session → RVT ONNX → AP, SeqASR) and
``report`` (JSON, markdown table, plot, annotated GIF). No torch needed."""
