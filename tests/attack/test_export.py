"""Print export: pattern pieces, PDF page geometry (page sizes, cell size in points), texture io, CLI."""

import json

import numpy as np
import pytest

from davis_rig.attack.export import (
    PAPER_SIZES_MM,
    PT_PER_MM,
    black_rectangles,
    export_texture,
    load_texture_grid,
    pattern_pieces,
    upsample,
)

pypdf = pytest.importorskip("pypdf", reason="pypdf (test extra) parses the written PDF")
pytest.importorskip("reportlab", reason="reportlab (extra 'export') writes the PDF")


def _filled_rects(page):
    """(w, h) of every `x y w h re` followed by a fill operator in a page's content stream."""
    from pypdf.generic import ContentStream

    ops = ContentStream(page.get_contents(), page.pdf).operations
    out, pending = [], []
    for operands, op in ops:
        if op == b"re":
            pending.append((float(operands[2]), float(operands[3])))
        elif op in (b"f", b"f*", b"F"):
            out += pending
            pending = []
        elif op in (b"n", b"S", b"W", b"W*", b"B"):
            pending = []
    return out


def test_black_rectangles_cover_black_cells_exactly():
    g = (np.random.default_rng(0).random((17, 13)) > 0.4).astype(float)
    count = np.zeros_like(g)
    for r0, c0, r1, c1 in black_rectangles(g):
        count[r0:r1, c0:c1] += 1
    assert count.max() == 1 and np.array_equal(count == 1, g <= 0.5)


def test_pieces_are_uv_islands_scaled_by_the_body():
    pieces = pattern_pieces()
    assert [p.name for p in pieces] == ["torso", "arms-1", "arms-2", "legs"]
    for p in pieces:
        assert len(p.loops_uv) >= 1 and not p.mirrored
        assert p.stretch_quartiles[0] <= p.mm_per_uv <= p.stretch_quartiles[2]
    user = pattern_pieces(["arms"], cell_mm=25.0, n_cells=10)
    assert all(p.cell_mm(10) == pytest.approx(25.0) for p in user)
    with pytest.raises(ValueError):
        pattern_pieces(["wings"])


@pytest.mark.parametrize("paper", ["A4", "A3"])
def test_pdf_pages_and_cell_size(tmp_path, paper):
    grid = np.ones((10, 10), dtype=np.float32)
    grid[::2, ::2] = 0  # isolated black cells: every filled rect is exactly one cell
    written = export_texture(grid, tmp_path, parts=("arms",), paper=paper, cell_mm=30.0, preview=False)
    reader = pypdf.PdfReader(str(written["pdf"]))
    info = json.loads(written["json"].read_text())
    assert len(reader.pages) == info["pages"] >= 2
    w_pt, h_pt = (v * PT_PER_MM for v in PAPER_SIZES_MM[paper])
    cell_pt = 30.0 * PT_PER_MM
    seen_cells = 0
    for page in reader.pages:
        box = sorted((float(page.mediabox.width), float(page.mediabox.height)))
        assert box == pytest.approx(sorted((w_pt, h_pt)), abs=1e-3)
    for page in reader.pages[1:]:  # tile pages (page 1 is the scaled-down overview)
        for w, h in _filled_rects(page):
            assert abs(w) == pytest.approx(cell_pt, abs=1e-3) and abs(h) == pytest.approx(cell_pt, abs=1e-3)
            seen_cells += 1
    assert seen_cells > 0
    pieces = {p["name"] for p in info["pieces"]}
    assert pieces == {"arms-1", "arms-2"}
    assert all(len(p["tiles"]) >= 1 for p in info["pieces"])  # every piece lands on some page


def test_texture_io_roundtrip(tmp_path):
    grid = (np.random.default_rng(3).random((12, 12)) > 0.5).astype(np.float32)
    np.save(tmp_path / "g.npy", grid)
    assert np.array_equal(load_texture_grid(tmp_path / "g.npy"), grid)
    import cv2

    cv2.imwrite(str(tmp_path / "m.png"), (upsample(grid, 1024) * 255).astype(np.uint8))
    assert np.array_equal(load_texture_grid(tmp_path / "m.png"), grid)  # grid size detected
    assert np.array_equal(load_texture_grid(tmp_path / "m.png", n_cells=12), grid)


def test_cli_export(tmp_path):
    from davis_rig.cli.attack import main

    np.save(tmp_path / "g.npy", np.zeros((4, 4), dtype=np.float32))
    code = main(["export", str(tmp_path / "g.npy"), "--out", str(tmp_path / "o"), "--parts", "arms",
                 "--size-mm", "400", "--no-preview"])
    assert code == 0 and (tmp_path / "o" / "pattern_A4.pdf").is_file()
    assert main(["export", str(tmp_path / "g.npy"), "--out", str(tmp_path / "o"), "--cell-mm", "-1"]) == 2


def test_tiles_join_only_printed_neighbours(tmp_path):
    # plan_tiles drops empty tiles (legs at 150 mm cells: 11 of 3 x 4 on A4); a tile page must not put
    # registration marks and a "joins" label on an edge whose neighbour was dropped
    import re

    from davis_rig.attack.export import Tile
    from davis_rig.attack.export.pdf import _joined_neighbours

    tile = Tile(0, 1, 1, 3, 3, 0.0, 0.0, 100.0, 100.0, False)
    kept = {(0, 0, 1), (0, 1, 1), (0, 1, 2), (1, 2, 1)}  # (1, 2, 1) belongs to another piece
    assert _joined_neighbours(tile, kept) == {"top": (0, 1), "right": (1, 2)}
    written = export_texture(np.ones((10, 10), np.float32), tmp_path, parts=("legs",), paper="A4", cell_mm=150.0,
                             preview=False)
    info = json.loads(written["json"].read_text())
    printed = {t["label"] for t in info["pieces"][0]["tiles"]}
    reader = pypdf.PdfReader(str(written["pdf"]))
    joins = set()
    for page in reader.pages[1:]:
        joins |= set(re.findall(r"joins legs ([A-Z]+\d+)", page.extract_text()))
    assert joins and joins <= printed
    assert len(printed) < 12  # the layout does drop a tile (else the test shows nothing)


def test_overview_clips_pieces_even_odd(tmp_path):
    # the module promises even-odd clipping (holes stay white) on every page: the overview used the non-zero rule
    from pypdf.generic import ContentStream

    written = export_texture(np.ones((10, 10), np.float32), tmp_path, parts=("arms",), preview=False)
    reader = pypdf.PdfReader(str(written["pdf"]))
    for page in reader.pages:
        ops = [op for _, op in ContentStream(page.get_contents(), page.pdf).operations]
        assert b"W*" in ops
    overview = [op for _, op in ContentStream(reader.pages[0].get_contents(), reader.pages[0].pdf).operations]
    assert b"W" not in overview  # every clip of the overview is a piece outline


def test_an_empty_or_zipped_npy_texture_is_a_format_error(tmp_path):
    from davis_rig.attack.export.grid import load_texture_grid
    from davis_rig.errors import FormatError

    (tmp_path / "empty.npy").write_bytes(b"")
    with pytest.raises(FormatError, match="empty.npy: not a readable .npy array"):
        load_texture_grid(tmp_path / "empty.npy")
    np.savez(tmp_path / "grid.npz", grid=np.ones((4, 4)))
    (tmp_path / "grid.npz").rename(tmp_path / "zipped.npy")
    with pytest.raises(FormatError, match="zipped.npy: an .npz archive, not a .npy array"):
        load_texture_grid(tmp_path / "zipped.npy")


def test_grids_of_one_cell_and_stacked_grids_load_and_other_shapes_are_format_errors(tmp_path):
    from davis_rig.attack.export.grid import load_texture_grid
    from davis_rig.errors import FormatError

    np.save(tmp_path / "one.npy", np.ones((1, 1), np.float32))  # what optimize --cells 1 writes
    np.testing.assert_array_equal(load_texture_grid(tmp_path / "one.npy"), [[1.0]])
    np.save(tmp_path / "stacked.npy", np.eye(4, dtype=np.float32)[None])  # [1, n, n]
    np.testing.assert_array_equal(load_texture_grid(tmp_path / "stacked.npy"), np.eye(4))
    for name, array in (("cube.npy", np.zeros((3, 10, 10))), ("scalar.npy", np.float32(1)),
                        ("empty.npy", np.zeros((0, 0)))):
        np.save(tmp_path / name, array)
        with pytest.raises(FormatError, match=name):
            load_texture_grid(tmp_path / name)


def test_a_print_wider_than_ten_metres_is_refused_before_any_page(tmp_path):
    from davis_rig.attack.export.pattern import pattern_pieces
    from davis_rig.errors import ConfigError

    with pytest.raises(ConfigError, match="would print 1e\\+06 mm wide"):
        pattern_pieces(("torso",), texture_mm=1e6)
    with pytest.raises(ConfigError, match="would print 2e\\+06 mm wide"):
        pattern_pieces(("torso",), cell_mm=2e5, n_cells=10)
    with pytest.raises(ConfigError, match="ease"):
        pattern_pieces(("torso",), ease=1e6)


def test_an_export_into_the_same_folder_leaves_no_file_of_the_earlier_print(tmp_path):
    from davis_rig.attack.export import export_texture

    grid = np.eye(10, dtype=np.float32)
    export_texture(grid, tmp_path, parts=("arms",), paper="A4", cell_mm=30.0, preview=False, map_size=256)
    (tmp_path / "notes.txt").write_text("mine")
    written = export_texture(grid, tmp_path, parts=("arms",), paper="A3", cell_mm=30.0, preview=False)
    assert not (tmp_path / "pattern_A4.pdf").exists() and not (tmp_path / "texture_256.png").exists()
    assert written["pdf"].name == "pattern_A3.pdf" and (tmp_path / "texture_1024.png").is_file()
    assert (tmp_path / "notes.txt").read_text() == "mine"  # not one of the export's own files


def test_texture_values_outside_zero_to_one_are_a_format_error(tmp_path):
    from davis_rig.attack.export.grid import load_texture_grid
    from davis_rig.errors import FormatError

    np.save(tmp_path / "bytes_as_floats.npy", np.eye(4, dtype=np.float32) * 255)  # would read as all white cells
    with pytest.raises(FormatError, match=r"values must lie in \[0, 1\] \(1 = white\), got 0..255"):
        load_texture_grid(tmp_path / "bytes_as_floats.npy")
    np.save(tmp_path / "ints.npy", np.eye(4, dtype=np.int64))  # 0/1 integers are a grid
    np.testing.assert_array_equal(load_texture_grid(tmp_path / "ints.npy"), np.eye(4))
