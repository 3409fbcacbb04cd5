"""RVT / YOLOX post-processing in numpy: confidence filter and class-wise NMS, exactly as the official code.

Reproduces ``models/detection/yolox/utils/boxes.py::postprocess`` (``class_agnostic=False``) with
``torchvision.ops.batched_nms`` semantics on CPU, in float32 like the original:

* boxes ``(cx, cy, w, h)`` → ``(x1, y1, x2, y2)`` = ``(cx − w/2, cy − h/2, cx + w/2, cy + h/2)``;
* ``class_conf, class_pred`` = max / argmax of the class probabilities (first index on ties);
* keep anchors with ``obj · class_conf ≥ conf_threshold`` (float32 comparison, like torch);
* class-wise greedy NMS on ``scores = obj · class_conf``: a box is suppressed when its IoU (float32, no +1)
  with a kept box of the same class is **> nms_threshold** (compared in float64, like the C++ kernel);
* torchvision's two CPU paths: with more than 1000 candidate boxes (> 4000 coordinates) it runs NMS per class
  and orders the union by decreasing score (``Tensor.sort``, which on CPU is libstdc++'s unstable
  ``std::sort`` — emulated here exactly, so even exact score ties come out in torch's order); otherwise it
  offsets every class's boxes by ``class · (max_coordinate + 1)`` and runs one NMS (stable descending sort).

Rows of the result: ``(x1, y1, x2, y2, obj, class_conf, class_pred)`` float32, ordered by decreasing
``obj · class_conf``; ``None`` for an image without detections. No top-k cap (the official code has none).

numpy only: torch tensors are accepted (converted with ``.detach().cpu().numpy()``) but torch is not imported.
"""

from __future__ import annotations

import numpy as np

from davis_rig.errors import ShapeError
from davis_rig.types import RVT_NMS_IOU

__all__ = ["batched_nms", "nms", "postprocess", "postprocess_thresholds", "torch_cpu_unstable_argsort_desc"]

#: torchvision ``batched_nms``: above this many box coordinates, CPU uses the per-class loop.
_CPU_VANILLA_COORDINATES = 4000


def _to_numpy(array) -> np.ndarray:
    if hasattr(array, "detach") and hasattr(array, "cpu"):  # a torch tensor, without importing torch
        array = array.detach().cpu().numpy()
    return np.asarray(array)


def _stable_argsort_desc(scores: np.ndarray) -> np.ndarray:
    """``torch.sort(stable=True, descending=True)`` indices: equal scores keep their original order."""
    # Sorting the negated values ascending with a stable sort gives a stable descending order (finite floats);
    # NaNs go first in torch's descending order.
    keys = -scores.astype(np.float64)
    nan = np.isnan(keys)
    if nan.any():
        keys = np.where(nan, -np.inf, keys)
    return np.argsort(keys, kind="stable")


def nms(boxes, scores, iou_threshold: float) -> np.ndarray:
    """Greedy NMS exactly like torchvision's CPU kernel (``nms_kernel.cpp``), float32 arithmetic.

    Args:
        boxes: float32 [N, 4] ``(x1, y1, x2, y2)``, pixels.
        scores: float32 [N].
        iou_threshold: boxes with IoU **>** this value (compared in float64) are suppressed.

    Returns:
        int64 [K] indices of kept boxes, by decreasing score (stable: ties keep index order).

    Raises:
        ShapeError: boxes not [N, 4] or scores not [N].
    """
    boxes = np.asarray(boxes, dtype=np.float32)
    scores = np.asarray(scores, dtype=np.float32)
    if boxes.ndim != 2 or boxes.shape[1] != 4 or scores.shape != (boxes.shape[0],):
        raise ShapeError(f"nms: expected boxes [N, 4] and scores [N], got {boxes.shape} and {scores.shape}")
    n = boxes.shape[0]
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    order = _stable_argsort_desc(scores)
    # Work in score order: position k is the k-th box the kernel visits.
    x1, y1, x2, y2 = (np.ascontiguousarray(boxes[order, k]) for k in range(4))
    with np.errstate(invalid="ignore", over="ignore"):  # NaN/inf boxes: NaN areas never suppress, as in C++
        areas = (x2 - x1) * (y2 - y1)
    rows, cols = _suppression_pairs(x1, y1, x2, y2, areas, float(iou_threshold))
    # Greedy pass (sequential by nature): a box not yet suppressed is kept and suppresses its later partners.
    row_starts = np.searchsorted(rows, np.arange(n + 1)).tolist()
    cols_list = cols.tolist()
    suppressed = bytearray(n)
    keep = []
    for pos in range(n):
        if suppressed[pos]:
            continue
        keep.append(pos)
        for other in cols_list[row_starts[pos] : row_starts[pos + 1]]:
            suppressed[other] = 1
    return order[np.asarray(keep, dtype=np.int64)].astype(np.int64)


def _float32_above(threshold: float) -> np.float32:
    """The float32 ``t`` with ``v > t`` ⟺ ``float64(v) > threshold`` for every float32 ``v``."""
    t32 = np.float32(threshold)
    if float(t32) > threshold:
        t32 = np.nextafter(t32, np.float32(-np.inf))
    return np.float32(t32)


#: Above this many sweep candidates the pairs are generated block by block instead (bounded memory).
_MAX_SWEEP_PAIRS = 4_000_000


def _overlap_candidates_sweep(x1, y1, x2, y2, n_pairs_limit: int):
    """Pairs ``(i, j)``, ``i < j``, whose boxes overlap strictly in x and y (sweep over boxes sorted by x1).

    For the box ``a`` earlier in x1 order, its partners are the boxes after it with ``x1 < x2_a`` (one
    ``searchsorted``); the 4 strict overlap conditions are then checked on those. Returns ``None`` when there
    would be more than ``n_pairs_limit`` sweep candidates.
    """
    n = x1.shape[0]
    by_x = np.argsort(x1, kind="stable")
    sorted_x1 = x1[by_x]
    ends = np.searchsorted(sorted_x1, x2[by_x], side="left")
    positions = np.arange(n)
    counts = np.maximum(ends - positions - 1, 0)
    total = int(counts.sum())
    if total > n_pairs_limit:
        return None
    if total == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    first = np.repeat(positions, counts)
    group_starts = np.repeat(np.cumsum(counts) - counts, counts)
    second = first + 1 + (np.arange(total) - group_starts)
    a, b = by_x[first], by_x[second]
    overlap = (x1[b] < x2[a]) & (x1[a] < x2[b]) & (y1[b] < y2[a]) & (y1[a] < y2[b])
    a, b = a[overlap], b[overlap]
    return np.minimum(a, b), np.maximum(a, b)


def _overlap_candidates_blocks(x1, y1, x2, y2, block_rows: int = 512):
    """Same pairs as :func:`_overlap_candidates_sweep`, from dense comparisons in row blocks (any overlap)."""
    n = x1.shape[0]
    rows, cols = [], []
    for start in range(0, n, block_rows):
        stop = min(start + block_rows, n)
        ax1, ay1, ax2, ay2 = x1[start:stop, None], y1[start:stop, None], x2[start:stop, None], y2[start:stop, None]
        candidate = (x1[None, start:] < ax2) & (ax1 < x2[None, start:])
        candidate &= (y1[None, start:] < ay2) & (ay1 < y2[None, start:])
        i, j = np.nonzero(candidate)
        i, j = i + start, j + start
        later = j > i
        rows.append(i[later])
        cols.append(j[later])
    return np.concatenate(rows), np.concatenate(cols)


def _suppression_pairs(x1, y1, x2, y2, areas, threshold: float):
    """All pairs (i < j, score order) whose IoU, computed like torchvision's kernel, is > ``threshold``.

    The IoU arithmetic is the kernel's, elementwise in float32 with the kept box as first operand:
    ``xx1 = max(x1_i, x1_j)`` (C++ ``std::max``), ``w = max(0, xx2 - xx1)``, ``inter = w·h``,
    ``ovr = inter / (area_i + area_j - inter)``. Only pairs whose extents overlap strictly are evaluated: any
    other pair gives ``inter = 0`` or NaN in the kernel, never a suppression. Returns ``(rows, cols)`` int64
    arrays sorted by row.
    """
    t32 = _float32_above(threshold)
    zero = np.float32(0)
    with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
        pairs = _overlap_candidates_sweep(x1, y1, x2, y2, _MAX_SWEEP_PAIRS)
        i, j = pairs if pairs is not None else _overlap_candidates_blocks(x1, y1, x2, y2)
        if i.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        xx1 = np.where(x1[i] < x1[j], x1[j], x1[i])
        yy1 = np.where(y1[i] < y1[j], y1[j], y1[i])
        xx2 = np.where(x2[j] < x2[i], x2[j], x2[i])
        yy2 = np.where(y2[j] < y2[i], y2[j], y2[i])
        w = xx2 - xx1
        h = yy2 - yy1
        w = np.where(zero < w, w, zero)
        h = np.where(zero < h, h, zero)
        inter = w * h
        ovr = inter / (areas[i] + areas[j] - inter)
        hit = ovr > t32
    i, j = i[hit], j[hit]
    order = np.argsort(i, kind="stable")
    return i[order].astype(np.int64), j[order].astype(np.int64)


def torch_cpu_unstable_argsort_desc(values) -> np.ndarray:
    """Indices of ``torch.sort(values, descending=True)`` on CPU (``stable=False``), ties included.

    PyTorch's CPU sort without ``stable=True`` runs libstdc++ ``std::sort`` (introsort: median-of-three
    quicksort down to 16-element blocks, heap sort past the depth limit, final insertion sort) on
    (value, index) pairs compared by value only. When no two values are equal the result is the plain
    descending order; otherwise the tie order of that algorithm is reproduced step by step.

    Args:
        values: float [N] (NaN sorts first, as in torch's descending comparator).

    Returns:
        int64 [N] permutation.
    """
    values = np.asarray(values)
    n = values.shape[0]
    order = _stable_argsort_desc(values)
    if n < 2:
        return order.astype(np.int64)
    sorted_values = values[order]
    nan = np.isnan(sorted_values)
    finite_ties = bool(np.any(sorted_values[1:] == sorted_values[:-1]))
    if not finite_ties and int(nan.sum()) <= 1:
        return order.astype(np.int64)
    return _introsort_desc(values)


def _introsort_desc(values: np.ndarray) -> np.ndarray:
    """Step-by-step emulation of libstdc++ ``std::sort`` with torch's descending comparator.

    torch's comparator (NaN first, then larger first) is replaced by integer ranks that compare the same way
    (equal floats and all NaNs share a rank, NaN ranks highest), and :func:`_libstdcxx_sort_keys` sorts them.
    """
    nan = np.isnan(values)
    ranks = np.empty(values.shape[0], dtype=np.int64)
    finite_unique, inverse = np.unique(values[~nan], return_inverse=True)
    ranks[~nan] = inverse
    ranks[nan] = finite_unique.shape[0]
    return np.asarray(_libstdcxx_sort_keys(ranks.tolist()), dtype=np.int64)


def _libstdcxx_sort_keys(keys: list) -> list:
    """libstdc++'s ``std::sort`` (introsort) of ``range(len(keys))`` with ``comp(a, b) = keys[a] > keys[b]``.

    Operation for operation the C++ library's algorithm (:class:`_Introsort`): median-of-three (``first+1``,
    middle, ``last-1``) quicksort with an unguarded partition down to 16-element ranges, heap sort once
    ``2·floor(log2 n)`` levels are exceeded, then a final insertion sort — so items whose keys compare equal end up
    in exactly the order the C++ library gives them. The keys move along with the items in a parallel list, so
    every comparison is one ``>`` on two list entries (the only operator used on the keys).

    Args:
        keys: the items' keys (ints for speed; any objects with ``>``) for the items ``0 .. n-1``.

    Returns:
        The items (indices) in sorted order: larger keys first, ties in libstdc++'s order.
    """
    return _Introsort(keys).sort()


class _Introsort:
    """The steps of libstdc++'s ``std::sort`` (``bits/stl_algo.h``, ``bits/stl_heap.h``) on a key list ``k`` and
    the parallel item list ``it``; ``first``/``last`` are indices into both, as the C++ iterators."""

    __slots__ = ("k", "it")

    #: libstdc++'s ``_S_threshold``: ranges this short are left to the final insertion sort.
    THRESHOLD = 16

    def __init__(self, keys: list):
        self.k = list(keys)
        self.it = list(range(len(self.k)))

    def sort(self) -> list:
        """``std::sort``: the introsort loop, then the final insertion sort; returns the sorted items."""
        n = len(self.k)
        if n < 2:
            return self.it
        self.introsort_loop(0, n, 2 * (n.bit_length() - 1))
        if n > self.THRESHOLD:
            self.insertion_sort(0, self.THRESHOLD)
            for i in range(self.THRESHOLD, n):
                self.unguarded_linear_insert(i)
        else:
            self.insertion_sort(0, n)
        return self.it

    def introsort_loop(self, first: int, last: int, depth_limit: int) -> None:
        """``__introsort_loop``: partition until ranges are short, heap sort when too deep."""
        k = self.k
        while last - first > self.THRESHOLD:
            if depth_limit == 0:
                self.heap_sort(first, last)
                return
            depth_limit -= 1
            self.move_median_to_first(first, first + 1, first + (last - first) // 2, last - 1)
            cut = self.unguarded_partition(first + 1, last, k[first])
            self.introsort_loop(cut, last, depth_limit)
            last = cut

    def move_median_to_first(self, result: int, a: int, b: int, c: int) -> None:
        """``__move_median_to_first``: swap the median of ``a, b, c`` into ``result``."""
        k, it = self.k, self.it
        ka, kb, kc = k[a], k[b], k[c]
        if ka > kb:
            pick = b if kb > kc else (c if ka > kc else a)
        elif ka > kc:
            pick = a
        elif kb > kc:
            pick = c
        else:
            pick = b
        k[result], k[pick] = k[pick], k[result]
        it[result], it[pick] = it[pick], it[result]

    def unguarded_partition(self, first: int, last: int, pivot_key) -> int:
        """``__unguarded_partition`` around ``pivot_key``; returns the cut."""
        k, it = self.k, self.it
        while True:
            while k[first] > pivot_key:
                first += 1
            last -= 1
            while pivot_key > k[last]:
                last -= 1
            if not first < last:
                return first
            k[first], k[last] = k[last], k[first]
            it[first], it[last] = it[last], it[first]
            first += 1

    def adjust_heap(self, first: int, hole: int, length: int, value_key, value_item) -> None:
        """``__adjust_heap``: sift the hole down to a leaf, then push the value back up (``__push_heap``)."""
        k, it = self.k, self.it
        top = hole
        child = hole
        while child < (length - 1) // 2:
            child = 2 * (child + 1)
            if k[first + child] > k[first + child - 1]:
                child -= 1
            k[first + hole], it[first + hole] = k[first + child], it[first + child]
            hole = child
        if (length & 1) == 0 and child == (length - 2) // 2:
            child = 2 * (child + 1)
            k[first + hole], it[first + hole] = k[first + child - 1], it[first + child - 1]
            hole = child - 1
        parent = (hole - 1) // 2
        while hole > top and k[first + parent] > value_key:
            k[first + hole], it[first + hole] = k[first + parent], it[first + parent]
            hole = parent
            parent = (hole - 1) // 2
        k[first + hole], it[first + hole] = value_key, value_item

    def heap_sort(self, first: int, last: int) -> None:
        """``__partial_sort(first, last, last)``: ``__make_heap`` then ``__sort_heap``."""
        k, it = self.k, self.it
        length = last - first
        if length >= 2:
            parent = (length - 2) // 2
            while True:
                self.adjust_heap(first, parent, length, k[first + parent], it[first + parent])
                if parent == 0:
                    break
                parent -= 1
        while last - first > 1:
            last -= 1
            value_key, value_item = k[last], it[last]
            k[last], it[last] = k[first], it[first]
            self.adjust_heap(first, 0, last - first, value_key, value_item)

    def unguarded_linear_insert(self, last: int) -> None:
        """``__unguarded_linear_insert``: move the item at ``last`` towards the front while it sorts first."""
        k, it = self.k, self.it
        value_key, value_item = k[last], it[last]
        nxt = last - 1
        while value_key > k[nxt]:
            k[last], it[last] = k[nxt], it[nxt]
            last = nxt
            nxt -= 1
        k[last], it[last] = value_key, value_item

    def insertion_sort(self, first: int, last: int) -> None:
        """``__insertion_sort`` of ``[first, last)``."""
        k, it = self.k, self.it
        for i in range(first + 1, last):
            if k[i] > k[first]:
                value_key, value_item = k[i], it[i]
                k[first + 1 : i + 1] = k[first:i]
                it[first + 1 : i + 1] = it[first:i]
                k[first], it[first] = value_key, value_item
            else:
                self.unguarded_linear_insert(i)


def _per_class_keep(boxes: np.ndarray, scores: np.ndarray, idxs: np.ndarray, iou_threshold: float) -> np.ndarray:
    """Indices (ascending) kept by greedy NMS run separately on each class; torchvision's per-class CPU path."""
    keep_mask = np.zeros(scores.shape[0], dtype=bool)
    for class_id in np.unique(idxs):
        members = np.flatnonzero(idxs == class_id)
        keep_mask[members[nms(boxes[members], scores[members], iou_threshold)]] = True
    return np.flatnonzero(keep_mask)


def batched_nms(boxes, scores, idxs, iou_threshold: float, *, path: str = "auto") -> np.ndarray:
    """Class-wise NMS with ``torchvision.ops.batched_nms`` semantics on CPU.

    Args:
        boxes: float32 [N, 4] ``(x1, y1, x2, y2)``, pixels.
        scores: float32 [N].
        idxs: class index per box, [N] (any real dtype; converted to float32 for the coordinate offsets).
        iou_threshold: IoU above which a box of the same class is suppressed.
        path: ``"auto"`` (torchvision's CPU choice: per-class loop when ``4·N > 4000``), ``"per_class"``
            or ``"offset"`` to force one path.

    Returns:
        int64 [K] kept indices, by decreasing score.

    Raises:
        ShapeError: inconsistent shapes. ValueError: unknown ``path``.
    """
    boxes = np.asarray(boxes, dtype=np.float32)
    scores = np.asarray(scores, dtype=np.float32)
    idxs = np.asarray(idxs)
    if boxes.ndim != 2 or boxes.shape[1] != 4 or scores.shape != (boxes.shape[0],) or idxs.shape != scores.shape:
        raise ShapeError(
            f"batched_nms: expected boxes [N, 4], scores [N], idxs [N]; got {boxes.shape}, {scores.shape}, "
            f"{idxs.shape}"
        )
    if path not in ("auto", "per_class", "offset"):
        raise ValueError(f"path: expected 'auto', 'per_class' or 'offset', got {path!r}")
    if boxes.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    if path == "per_class" or (path == "auto" and boxes.size > _CPU_VANILLA_COORDINATES):
        keep = _per_class_keep(boxes, scores, idxs, iou_threshold)
        return keep[torch_cpu_unstable_argsort_desc(scores[keep])]
    max_coordinate = boxes.max()
    with np.errstate(invalid="ignore", over="ignore"):
        offsets = idxs.astype(np.float32) * (max_coordinate + np.float32(1))
        shifted = boxes + offsets[:, None]
    return nms(shifted, scores, iou_threshold)


def _candidates(pred: np.ndarray, num_classes: int, threshold: np.float32):
    """Rows of one image passing ``obj · class_conf ≥ threshold``: (float32 [K, 7] detections, float32 [K] scores).

    ``pred`` is float32 [A, 5 + classes]; rows keep the anchor order, columns ``(x1, y1, x2, y2, obj,
    class_conf, class_pred)`` with the official corner conversion (``cx ∓ w / 2`` in float32).
    """
    class_probs = pred[:, 5 : 5 + num_classes]
    class_pred = np.argmax(class_probs, axis=1)
    class_conf = np.take_along_axis(class_probs, class_pred[:, None], axis=1)[:, 0]
    obj = pred[:, 4]
    keep = np.flatnonzero(obj * class_conf >= threshold)
    rows = pred[keep]
    half_w = rows[:, 2] / np.float32(2)
    half_h = rows[:, 3] / np.float32(2)
    detections = np.stack(
        [rows[:, 0] - half_w, rows[:, 1] - half_h, rows[:, 0] + half_w, rows[:, 1] + half_h,
         rows[:, 4], class_conf[keep], class_pred[keep].astype(np.float32)],
        axis=1,
    )
    return detections, detections[:, 4] * detections[:, 5]


def _image_thresholds(detections: np.ndarray, scores: np.ndarray, thresholds: list, nms_threshold: float) -> list:
    """Post-processed output of one image at every threshold (ascending), sharing the NMS work exactly.

    Greedy NMS visits boxes by decreasing score and a box's fate depends only on the boxes before it, so the
    result at a higher threshold is the result at a lower one restricted to ``score ≥ threshold`` — provided
    both run the same IoU arithmetic: torchvision's per-class path (raw boxes) always, its offset path only
    when the class offsets (``max coordinate + 1``) are equal. The per-class result is then re-ordered with
    torch's unstable sort of the kept scores, as :func:`batched_nms` does. Anything else is recomputed.
    """
    outputs, previous_count, previous = [], -1, None
    per_class_keep = None  # sorted candidate rows kept by per-class NMS at a lower threshold
    offset_key, offset_order = None, None  # (max coordinate, kept rows in output order) of the offset path
    for threshold in thresholds:
        members = np.flatnonzero(scores >= np.float32(threshold))
        count = members.shape[0]
        if count != previous_count:
            previous_count = count
            if count == 0:
                previous = None
            elif 4 * count > _CPU_VANILLA_COORDINATES:  # torchvision's per-class path
                if per_class_keep is None:
                    per_class_keep = members[_per_class_keep(detections[members, :4], scores[members],
                                                             detections[members, 6], nms_threshold)]
                    keep = per_class_keep
                else:
                    keep = per_class_keep[scores[per_class_keep] >= np.float32(threshold)]
                previous = detections[keep[torch_cpu_unstable_argsort_desc(scores[keep])]]
            else:  # offset path: exact reuse only with the same class offsets
                key = detections[members, :4].max()
                if offset_order is not None and key == offset_key:
                    order = offset_order[scores[offset_order] >= np.float32(threshold)]
                else:
                    order = members[batched_nms(detections[members, :4], scores[members], detections[members, 6],
                                                nms_threshold, path="offset")]
                    offset_key, offset_order = key, order
                previous = detections[order]
        outputs.append(previous)
    return outputs


def postprocess_thresholds(
    decoded,
    conf_thresholds,
    nms_threshold: float = RVT_NMS_IOU,
    *,
    num_classes: int | None = None,
) -> dict[float, list[np.ndarray | None]]:
    """:func:`postprocess` at several confidence thresholds at once, identical to one call per threshold.

    The confidence filter runs once at the lowest threshold; NMS results are shared between thresholds
    wherever that is exact (see :func:`_image_thresholds`): with a random-weight RVT (all 1680 anchors above
    every paper threshold) one NMS serves all four thresholds. Equal outputs of two thresholds are the same
    array object (treat them as read-only).

    Args:
        decoded: float [B, A, 5 + num_classes], as for :func:`postprocess`.
        conf_thresholds: iterable of thresholds (obj · max class prob), any order, duplicates ignored.
        nms_threshold: class-wise IoU threshold.
        num_classes: number of class columns; default ``decoded.shape[-1] - 5``.

    Returns:
        ``{threshold (float): [B entries: float32 [K, 7] or None]}``, each list equal to
        ``postprocess(decoded, threshold, nms_threshold)``.

    Raises:
        ShapeError: ``decoded`` is not [B, A, 5 + num_classes]. ValueError: no threshold given.
    """
    pred = _to_numpy(decoded)
    if pred.ndim != 3 or pred.shape[-1] < 6:
        raise ShapeError(f"decoded: expected [B, A, 5 + num_classes], got {pred.shape}")
    if num_classes is None:
        num_classes = pred.shape[-1] - 5
    if pred.shape[-1] < 5 + num_classes or num_classes < 1:
        raise ShapeError(f"decoded: expected last dim >= 5 + {num_classes}, got {pred.shape}")
    thresholds = sorted({float(t) for t in conf_thresholds})
    if not thresholds:
        raise ValueError("conf_thresholds: expected at least one threshold")
    pred = pred.astype(np.float32, copy=False)
    per_image = []
    for image in range(pred.shape[0]):
        detections, scores = _candidates(pred[image], num_classes, np.float32(thresholds[0]))
        per_image.append(_image_thresholds(detections, scores, thresholds, nms_threshold))
    return {threshold: [outputs[i] for outputs in per_image] for i, threshold in enumerate(thresholds)}


def postprocess(
    decoded,
    conf_threshold: float,
    nms_threshold: float = RVT_NMS_IOU,
    *,
    num_classes: int | None = None,
) -> list[np.ndarray | None]:
    """Official RVT post-processing of the decoded head output (confidence filter + class-wise NMS).

    Args:
        decoded: float [B, A, 5 + num_classes] ``(cx, cy, w, h, obj_prob, class probs...)`` in input pixels
            (the output of ``RVTDetector.forward_detect`` or of the ONNX graph); numpy array or torch tensor.
            It is not modified (the official code modifies its input in place; this one copies).
        conf_threshold: keep anchors with ``obj · max class prob ≥ conf_threshold`` (0.001 for the reported
            Gen1 evaluation, 0.1 by default in RVT).
        nms_threshold: class-wise IoU threshold (boxes with IoU > it are suppressed).
        num_classes: number of class columns; default ``decoded.shape[-1] - 5``.

    Returns:
        One entry per image: float32 [K, 7] rows ``(x1, y1, x2, y2, obj, class_conf, class_pred)`` by
        decreasing ``obj · class_conf``, or ``None`` when nothing passes.

    Raises:
        ShapeError: ``decoded`` is not [B, A, 5 + num_classes].

    Example:
        >>> det = np.array([[[50, 50, 20, 20, 0.9, 0.1, 0.8], [52, 50, 20, 20, 0.9, 0.2, 0.7]]], np.float32)
        >>> out = postprocess(det, conf_threshold=0.1)
        >>> out[0].shape, out[0][0, 6]
        ((1, 7), np.float32(1.0))
    """
    return postprocess_thresholds(decoded, [conf_threshold], nms_threshold, num_classes=num_classes)[
        float(conf_threshold)
    ]
