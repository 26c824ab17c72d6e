"""Run the benchmarks that need no input beyond this tree and ``../shared/data``, one after another.

Each prints medians and ratios against a baseline measured in the same run. Not run here (they need
a second tree, a dataset, a refined scene or a browser): ``bench_ab.py``, ``bench_pose.py recipe``,
``bench_depth.py accuracy|figure|fusion``, ``bench_outputs.py teleop``, ``check_align_perturbed.py``,
``check_render_quality.py lod``, ``check_outputs_identical.py`` (a fingerprint, compared across
trees). ``--quick`` runs every one with tiny sizes (a smoke run: seconds each, numbers meaningless).

    python benchmarks/run_all.py              # minutes to an hour on a laptop
    python benchmarks/run_all.py --quick      # smoke run
    python benchmarks/run_all.py --only bench_render.py,bench_pose.py --json-dir out/bench
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent

RUNS: tuple[tuple[str, tuple[str, ...], tuple[str, ...]], ...] = (
    # (script, arguments of a full run, arguments of a smoke run)
    ("bench_render.py", (), ("--quick",)),
    ("bench_render.py", ("--compare-blend", "--sizes", "640x480"), ("--compare-blend", "--quick")),
    ("bench_render.py", ("--fill", "--sizes", "640x480", "--scene", "SAMPLE"), ("--fill", "--quick")),
    ("bench_sim.py", ("steps",), ("steps", "--quick")),
    ("bench_sim.py", ("envs",), ("envs", "--quick")),
    ("bench_sim.py", ("memory",), ("memory", "--quick")),
    ("bench_outputs.py", ("sinks",), ("sinks", "--quick")),
    ("bench_pose.py", ("metrics",), ("metrics", "--quick")),
    ("bench_pose.py", ("nets",), ("nets", "--quick")),
    ("bench_depth.py", ("refine",), ("refine", "--quick")),
    ("bench_generate.py", ("sample-scene",), ("sample-scene", "--quick")),
    ("bench_generate.py", ("gen-bop",), ("gen-bop", "--quick")),
    ("check_render_quality.py", ("zoom",), ("zoom", "--quick")),
)
"""``SAMPLE`` in the arguments stands for the sample scene folder (built once by ``benchmarks.common``)."""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="smoke run: tiny sizes")
    ap.add_argument("--only", default="", help="comma-separated script names to run (default: all)")
    ap.add_argument("--json-dir", type=Path, help="each run writes --json here (scripts that take --json)")
    ap.add_argument("--list", action="store_true", help="print the commands and exit")
    args = ap.parse_args(argv)
    only = {s for s in args.only.split(",") if s}
    unknown = only - {r[0] for r in RUNS}
    if unknown:
        ap.error(f"--only: unknown script(s) {sorted(unknown)}; choose from {sorted({r[0] for r in RUNS})}")
    failed = []
    for k, (script, full, quick) in enumerate(RUNS):
        if only and script not in only:
            continue
        run_args = list(quick if args.quick else full)
        if "SAMPLE" in run_args:
            sys.path.insert(0, str(HERE.parent))
            from benchmarks import common

            run_args[run_args.index("SAMPLE")] = str(common.sample_scene())
        if args.json_dir is not None and script not in ("bench_pose.py", "bench_depth.py", "bench_generate.py"):
            args.json_dir.mkdir(parents=True, exist_ok=True)
            run_args += ["--json", str(args.json_dir / f"{k:02d}_{Path(script).stem}.json")]
        cmd = [sys.executable, str(HERE / script), *run_args]
        print(f"\n===== {script} {' '.join(run_args)}", flush=True)
        if args.list:
            continue
        if subprocess.call(cmd) != 0:
            failed.append(f"{script} {' '.join(run_args)}")
    if failed:
        print(f"failed: {'; '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
