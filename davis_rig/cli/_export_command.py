"""``davis-attack export``: print-ready PDF pattern pieces, PNG textures and a preview of a texture.

Maps its arguments onto :func:`davis_rig.attack.export.export_texture`; heavy imports happen in the action.
"""

from __future__ import annotations

import argparse

from davis_rig.cli.common import add_out, epilog, non_negative_int, positive_float, positive_int

EXAMPLES = """\
examples:
  davis-attack export best_10x10.png --out print/                    # body-sized pieces, A4
  davis-attack export texture_1024.png --cells 10 --out print/ --paper A3 --size-mm 1000
  davis-attack export grid.npy --out print/ --cell-mm 50 --parts torso arms
"""
#: Body parts a pattern can be cut for (:data:`davis_rig.scene.body.PART_NAMES`).
EXPORT_PARTS = ("torso", "arms", "legs", "head", "hands", "feet")


def add_export_parser(subparsers) -> argparse.ArgumentParser:
    """Register ``export`` on the ``davis-attack`` subparsers."""
    p = subparsers.add_parser("export", help="print-ready vector PDF pattern pieces + PNGs + preview",
                              description="Lay a black/white texture out as body-part pattern pieces on A4/A3 pages.",
                              epilog=epilog(EXAMPLES), formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("texture", metavar="TEXTURE", help="n x n grid or upsampled map (.png/.npy), 1 = white")
    add_out(p, required=True, metavar="DIR", help="output directory")
    p.add_argument("--paper", default="A4", choices=["A4", "A3"])
    size = p.add_mutually_exclusive_group()
    size.add_argument("--size-mm", type=positive_float, default=None,
                      help="side of the whole UV texture in mm (official: 500 or 1000); default: the body's size")
    size.add_argument("--cell-mm", type=positive_float, default=None, help="side of one grid cell in mm")
    p.add_argument("--cells", type=positive_int, default=None,
                   help="grid cells per side of an upsampled map (auto-detected)")
    p.add_argument("--parts", nargs="+", choices=EXPORT_PARTS, default=["torso", "arms", "legs"], metavar="PART",
                   help="painted body parts: torso, arms, legs, head, hands, feet (default: torso arms legs)")
    p.add_argument("--shape", type=non_negative_int, default=0, help="body shape index for the body scale (default 0)")
    p.add_argument("--ease", type=positive_float, default=1.0, help="factor on the body scale (default 1.0)")
    p.add_argument("--no-preview", action="store_true", help="skip the preview render")
    p.set_defaults(func=export_command)
    return p


def export_command(args) -> int:
    """Run ``davis-attack export``; prints the written files."""
    from pathlib import Path

    from davis_rig.attack.export import export_texture, load_texture_grid
    from davis_rig.cli.common import removing_new_empty_dirs
    from davis_rig.errors import FormatError

    if Path(args.out).exists() and not Path(args.out).is_dir():
        raise FormatError(f"{args.out}: --out is a file; the pattern pieces need an output folder")
    grid = load_texture_grid(args.texture, args.cells)
    with removing_new_empty_dirs(args.out):
        written = export_texture(grid, args.out, parts=args.parts, paper=args.paper, texture_mm=args.size_mm,
                                 cell_mm=args.cell_mm, shape_index=args.shape, ease=args.ease,
                                 preview=not args.no_preview)
    for key, path in written.items():
        print(f"{key}: {path}")
    return 0
