"""``presim recover``: make what a killed recording wrote readable (MCAP, .rrd, capture folder)."""

from __future__ import annotations

import sys
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser(
        "recover", help="recover a recording killed before it closed (*.mcap.partial, *.rrd.partial, capture.partial/)",
        description="A recording killed with SIGKILL (or a power cut) leaves its outputs under *.partial. This keeps "
                    "every complete part: the MCAP's complete chunks rewritten with an index (mcap's make_reader and "
                    "ros2 bag read it), the .rrd cut after its last complete message, the capture folder's complete "
                    "frames; each is then renamed to its final name. See docs/outputs.md.")
    p.add_argument("dir", type=Path, help="the --record folder (or one *.partial file or folder)")
    p.add_argument("--overwrite", action="store_true", help="replace a complete output of the same name")
    p.set_defaults(func=_recover)


def _recover(args) -> int:
    from presim.outputs.recover import recover_dir

    done = recover_dir(args.dir, overwrite=args.overwrite, log=lambda s: print(s, file=sys.stderr))
    if not done:
        print(f"{args.dir}: nothing to recover (no *.partial)", file=sys.stderr)
    for r in done:
        unit = "frames" if r.kind == "capture" else "messages"
        print(f"recovered {r.path}: {r.kept} {unit} kept, {r.dropped_bytes} bytes of an incomplete tail left out")
    return 0
