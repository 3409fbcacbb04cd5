"""Detection metrics of the physical evaluation: ``ap`` (COCO AP, RVT/Prophesee protocol) and ``seqasr``.

numpy only at import; ``faster-coco-eval`` (or ``pycocotools``) is imported when AP is computed.
"""
