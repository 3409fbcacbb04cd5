"""Physical evaluation of recordings (the paper's Table 3): ``physical`` (session → RVT ONNX → AP, SeqASR),
``windows`` (the window grid the evaluation, the viewer and the RVT export share) and ``report`` (JSON, markdown
table, plot, annotated GIF). No torch needed."""
