"""UV islands of the export: connected components of faces that share a UV vertex."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from davis_rig.attack.export.pattern import _islands


def _components_by_search(faces: np.ndarray) -> list[list[int]]:
    """Reference: depth-first search over faces sharing a vertex (plain Python)."""
    by_vertex: dict[int, list[int]] = {}
    for index, face in enumerate(faces.tolist()):
        for vertex in face:
            by_vertex.setdefault(vertex, []).append(index)
    seen, groups = set(), []
    for start in range(len(faces)):
        if start in seen:
            continue
        stack, group = [start], []
        seen.add(start)
        while stack:
            face = stack.pop()
            group.append(face)
            for vertex in faces[face].tolist():
                for other in by_vertex[vertex]:
                    if other not in seen:
                        seen.add(other)
                        stack.append(other)
        groups.append(sorted(group))
    return sorted(groups, key=lambda g: (-len(g), g[0]))


def test_two_strips_and_a_lone_triangle():
    faces = np.array([[0, 1, 2], [10, 11, 12], [2, 3, 4], [4, 5, 6], [12, 13, 14], [20, 21, 22]])
    assert [g.tolist() for g in _islands(faces)] == [[0, 2, 3], [1, 4], [5]]


def test_a_long_chain_is_one_island():
    faces = np.stack([np.arange(500), np.arange(500) + 1, np.arange(500) + 1000], axis=1)[::-1].copy()
    assert [g.tolist() for g in _islands(faces)] == [list(range(500))]


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(*(st.integers(0, 40),) * 3), min_size=1, max_size=60))
def test_islands_equal_a_graph_search(rows):
    faces = np.array(rows, dtype=np.int64)
    assert [g.tolist() for g in _islands(faces)] == _components_by_search(faces)
