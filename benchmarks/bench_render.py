"""Steady-state rendering speed of the synthesis engine vs a naive numpy z-buffer, in one run.

For each scene and output size: a trajectory of novel poses (midpoints between consecutive captured
views, so every frame is a new pose near the capture; ``common.trajectory``) is rendered with the
full pipeline (``RenderConfig()``, ``PerfConfig()`` unless ``--backend``/``--threads`` say
otherwise), after a warm-up that compiles/loads what is needed. For every frame the naive baseline
(:func:`presim.testing.naive.naive_zbuffer`: vectorized numpy unproject -> project
-> lexsort z-buffer of whole frames, no layers, no filtering, no fill) splats the SAME views the
pipeline used, so the ratio compares implementations, not view counts. Steady state = the second
pass over the trajectory (every view it needs already prepared and cached); the first (cold) pass,
which also reads and prepares views, is reported per frame too.

Each case is also measured with "today" = ``RenderConfig(lod_levels=0, reuse_move_m=0)`` (no level
of detail, no selection reuse) in the same process, measured passes alternating with the default
config (``--passes``), reported as ``results[...]["today"]``, ``speedup_vs_today`` (wall) and
``cpu_speedup_vs_today``; ``--no-today`` skips it.

Prints medians of wall ms/frame, frames/s, per-stage wall ms, views per frame, hole fraction, the
ratio baseline/pipeline, the CPU time per frame (process time summed over threads: on a machine
shared with other jobs it is the robust number; with NUMBA_NUM_THREADS=1 it equals the wall time
of an unloaded core), and the peak RSS of the process (numba's allocations bypass tracemalloc).
The JSON (``--json``) holds ``results`` keyed ``"NAME WxH"`` (NAME = the scene folder's name) with
``fps_median``, ``ms_median``, ``cpu_ms_median``, ...: the speed check of two trees runs each tree's
own copy of this script with the same arguments (``bench_ab.py --bench-render``).

Other modes (one per run, on the same scenes, sizes and trajectory):

- ``--compare-blend``: the default pipeline against blending, sharpness-aware views and photometric
  correction (``RenderConfig(blend=True, sharpness=True)`` on the scene with a photometric
  calibration, matching frame 0's exposure), passes alternating; the in-run ratio of the medians
  (blend / base, wall and CPU) and both configs' per-stage medians.
- ``--fill``: the final fill's Telea kernel (:func:`presim.imaging.inpaint.telea_inpaint`) against
  its reference ``cv2.inpaint``, on the colour and hole mask of each frame rendered with
  ``fill_holes=False`` whose holes are at most ``--max-hole-frac`` of the image (the frames where
  ``fill_method="auto"`` runs Telea); alternating repeats; exits 1 when the outputs differ.
- ``--calls``: what the main per-frame functions cost inside the render loop against the same calls
  repeated alone, warm in the caches (their ratio is what running between the frame's kernels costs
  a call: the kernels stream about 1 MB per view through the L2, so the small numpy / OpenCV calls
  between them start cold).

    python benchmarks/bench_render.py                 # synthetic room + apc capture, 640x480 and 1280x720
    python benchmarks/bench_render.py --scene out/apc --sizes 640x480,128x128 --no-today --json out/r.json
    python benchmarks/bench_render.py --compare-blend --sizes 640x480
    python benchmarks/bench_render.py --scene out/sample --fill --sizes 640x480
    python benchmarks/bench_render.py --scene out/apc --calls --sizes 128x128
    python benchmarks/bench_render.py --backend torch --device cuda --no-today --sizes 640x480,128x128
    python benchmarks/bench_render.py --quick         # smoke run: synthetic room, 64x48, 3 frames
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402


# ---- speed: pipeline vs naive z-buffer (and "today") ---------------------------------------

def _measure(r, K, poses: np.ndarray, acc: dict) -> None:
    """One measured pass over ``poses``; appends per-frame numbers to ``acc``."""
    for T in poses:
        t0, c0 = time.perf_counter(), time.process_time()
        out = r.render(T, K)
        acc["ms"].append((time.perf_counter() - t0) * 1e3)
        acc["cpu_ms"].append((time.process_time() - c0) * 1e3)
        for s in acc["stages"]:
            acc["stages"][s].append(r.last.ms.get(s, 0.0))
        acc["views"].append(len(r.last.views))
        acc["holes"].append(out.hole_frac_before_fill)
        acc["lods"].extend(r.last.lod_levels)
        acc["used_views"].append(list(r.last.views))


def _new_acc() -> dict:
    from presim.synthesis.renderer import STAGES

    return {"ms": [], "cpu_ms": [], "views": [], "holes": [], "lods": [], "used_views": [],
            "stages": {s: [] for s in STAGES + ("upsample",)}}


def _summary(acc: dict) -> dict:
    med = float(np.median(acc["ms"]))
    return {
        "ms_median": med, "fps_median": 1e3 / med, "ms_p90": float(np.percentile(acc["ms"], 90)),
        "cpu_ms_median": float(np.median(acc["cpu_ms"])),
        "stages_ms_median": {s: round(float(np.median(v)), 2) for s, v in acc["stages"].items()},
        "views_mean": float(np.mean(acc["views"])),
        "lod_level_mean": float(np.mean(acc["lods"])) if acc["lods"] else 0.0,
        "hole_frac_mean": float(np.mean(acc["holes"])), "frames": len(acc["ms"]),
    }


def bench(scene, K, poses: np.ndarray, warmup: int, config, perf, today=None, passes: int = 2) -> dict:
    """Steady-state numbers of ``config``; with ``today``, the same for that config in the same run,
    measured passes alternating (config, today, config, today, ...) so load changes hit both."""
    from presim.testing.naive import naive_zbuffer
    from presim.synthesis.renderer import Renderer

    rs = {"new": Renderer(scene, config, perf)}
    if today is not None:
        rs["today"] = Renderer(scene, today, perf)
    cold = {}
    for name, r in rs.items():
        # Cold pass: compiles (first case only) and prepares every view the trajectory needs.
        t0 = time.perf_counter()
        for T in poses:
            r.render(T, K)
        cold[name] = (time.perf_counter() - t0) * 1e3 / len(poses)
        for T in poses[:warmup]:
            r.render(T, K)
    accs = {name: _new_acc() for name in rs}
    for _ in range(passes):
        for name, r in rs.items():
            _measure(r, K, poses, accs[name])
    res = _summary(accs["new"])
    r = rs["new"]
    res.update({"cache_mb": r.executor.cache.nbytes / 2**20, "cold_pass_ms_per_frame": cold["new"]})
    # The baseline in its own pass over the same poses and views (interleaving it with the
    # pipeline frame by frame evicted the pipeline's caches and parked its threads: +50 % per frame).
    frames, base_ms, base_cpu = {}, [], []
    for T, vs in zip(poses, accs["new"]["used_views"]):
        used = []
        for v in vs:
            if v not in frames:
                frames[v] = scene.frames.load(v)
            used.append((*frames[v], scene.intrinsics[v], scene.T_world_cam[v]))
        ms, cpu, _ = common.timed(lambda: naive_zbuffer(used, T, K))
        base_ms.append(ms)
        base_cpu.append(cpu)
    res.update({
        "baseline_ms_median": float(np.median(base_ms)),
        "speedup_vs_naive": float(np.median(base_ms) / res["ms_median"]),
        "baseline_cpu_ms_median": float(np.median(base_cpu)),
        "cpu_speedup_vs_naive": float(np.median(base_cpu) / res["cpu_ms_median"]),
    })
    if today is not None:
        old = _summary(accs["today"])
        res["today"] = old
        res["speedup_vs_today"] = old["ms_median"] / res["ms_median"]
        res["cpu_speedup_vs_today"] = old["cpu_ms_median"] / res["cpu_ms_median"]
    for r in rs.values():
        r.close()
    return res


def _print_speed(name: str, size: str, res: dict) -> None:
    st = " ".join(f"{k}={v:.1f}" for k, v in res["stages_ms_median"].items() if v > 0)
    print(f"{name:26s} {size:9s} {res['ms_median']:7.1f} ms  {res['fps_median']:5.1f} fps  "
          f"naive {res['baseline_ms_median']:7.1f} ms  x{res['speedup_vs_naive']:.1f}  "
          f"views {res['views_mean']:.1f}  holes {res['hole_frac_mean']:.4f}  | {st}")
    print(f"{'':26s} {'':9s} CPU {res['cpu_ms_median']:7.1f} ms/frame (all threads)  naive CPU "
          f"{res['baseline_cpu_ms_median']:7.1f} ms  x{res['cpu_speedup_vs_naive']:.1f}  "
          f"cold pass {res['cold_pass_ms_per_frame']:.0f} ms/frame  cache {res['cache_mb']:.0f} MB  "
          f"lod level {res['lod_level_mean']:.2f}")
    if "today" in res:
        old = res["today"]
        print(f"{'':26s} {'':9s} today (lod_levels=0, no reuse) {old['ms_median']:7.1f} ms "
              f"{old['fps_median']:5.1f} fps  CPU {old['cpu_ms_median']:7.1f} ms  -> wall "
              f"x{res['speedup_vs_today']:.2f}  CPU x{res['cpu_speedup_vs_today']:.2f}  | " + " ".join(
                  f"{k}={v:.1f}" for k, v in old["stages_ms_median"].items() if v > 0))


# ---- --compare-blend ---------------------------------------------------------------------------

def compare_blend(scene, K, poses: np.ndarray, warmup: int, perf, passes: int = 2) -> dict:
    """Default pipeline vs blending + sharpness + photometric correction, in one process: a cold
    pass and a warm-up per config, then measured passes alternating (base, blend, base, blend, ...)."""
    from presim.photometric import calibrate_photometric
    from presim.synthesis.renderer import RenderConfig, Renderer

    t0 = time.perf_counter()
    calib = calibrate_photometric(scene, show_progress=False)
    calib_s = time.perf_counter() - t0
    photo_scene = dataclasses.replace(scene, photometric=calib)
    rs = {"base": Renderer(scene, RenderConfig(), perf),
          "blend": Renderer(photo_scene, RenderConfig(blend=True, sharpness=True,
                                                      exposure_frame=scene.frame_ids[0]), perf)}
    for r in rs.values():
        for T in list(poses) + list(poses[:warmup]):  # cold pass (prepares every view) + warm-up
            r.render(T, K)
    accs = {k: _new_acc() for k in rs}
    for _ in range(passes):
        for k, r in rs.items():
            _measure(r, K, poses, accs[k])
    sm = {k: _summary(a) for k, a in accs.items()}
    med = {k: v["ms_median"] for k, v in sm.items()}
    cpu = {k: v["cpu_ms_median"] for k, v in sm.items()}
    return {"base_ms": med["base"], "blend_ms": med["blend"], "ratio_wall": med["blend"] / med["base"],
            "base_cpu_ms": cpu["base"], "blend_cpu_ms": cpu["blend"], "ratio_cpu": cpu["blend"] / cpu["base"],
            "blend_stage_ms": sm["blend"]["stages_ms_median"]["blend"],
            "stages_ms_median": {k: v["stages_ms_median"] for k, v in sm.items()},
            "views_mean": {k: v["views_mean"] for k, v in sm.items()},
            "photometric_calibration_s": calib_s, "frames": len(poses), "passes": passes}


def _print_blend(name: str, size: str, res: dict, n_frames: int) -> None:
    print(f"{name:26s} {size:9s} base {res['base_ms']:7.1f} ms  blend+sharp+photo {res['blend_ms']:7.1f} ms  "
          f"ratio {res['ratio_wall']:.3f} (CPU {res['base_cpu_ms']:.1f} -> {res['blend_cpu_ms']:.1f} ms, "
          f"ratio {res['ratio_cpu']:.3f})  blend stage {res['blend_stage_ms']:.1f} ms  "
          f"calibration {res['photometric_calibration_s']:.1f} s for {n_frames} frames")
    for k, st in res["stages_ms_median"].items():
        print(f"{'':26s} {k:9s} views {res['views_mean'][k]:.2f} | " + " ".join(
            f"{s}={x:.1f}" for s, x in st.items() if x > 0))


# ---- --fill: Telea kernel vs cv2.inpaint -------------------------------------------------------

def compare_fill(scene, K, poses: np.ndarray, perf, repeats: int, max_hole_frac: float) -> dict:
    """Per frame with few holes: median ms of cv2.inpaint (the reference) and of the numba Telea
    kernel, alternating halves of the repeats; whether the outputs are equal."""
    import cv2

    from presim.synthesis.renderer import RenderConfig, Renderer
    from presim.imaging.inpaint import telea_inpaint

    r = Renderer(scene, RenderConfig(fill_holes=False), perf)
    rows = []
    for k, T in enumerate(poses):
        o = r.render(T, K)
        color, holes = o.color.copy(), ~o.valid
        n = int(holes.sum())
        if n == 0 or n > max_hole_frac * holes.size:
            continue
        cv_list, nb_list = [], []
        for _ in range(2):  # alternate the two, half the repeats each time
            m, a = common.median_ms(lambda: cv2.inpaint(color, holes.view(np.uint8), 3, cv2.INPAINT_TELEA),
                                    max(1, repeats // 2))
            cv_list.append(m)
            m, b = common.median_ms(lambda: telea_inpaint(color, holes, 3), max(1, repeats // 2))
            nb_list.append(m)
        cv_ms, nb_ms = common.median(cv_list), common.median(nb_list)
        rows.append({"frame": k, "hole_px": n, "hole_frac": n / holes.size, "cv2_ms": cv_ms, "numba_ms": nb_ms,
                     "ratio": cv_ms / nb_ms, "equal": bool(np.array_equal(a, b))})
    r.close()
    if not rows:
        return {"frames": 0, "all_equal": True, "rows": []}
    return {"frames": len(rows), "ratio_median": common.median(x["ratio"] for x in rows),
            "cv2_us_per_hole_px_median": common.median(1e3 * x["cv2_ms"] / x["hole_px"] for x in rows),
            "numba_us_per_hole_px_median": common.median(1e3 * x["numba_ms"] / x["hole_px"] for x in rows),
            "all_equal": all(x["equal"] for x in rows), "rows": rows}


def _print_fill(name: str, size: str, res: dict) -> None:
    if not res["frames"]:
        print(f"{name:26s} {size:9s} no frame with holes within --max-hole-frac")
        return
    print(f"{name:26s} {size:9s} {res['frames']} frames: cv2 / numba median x{res['ratio_median']:.2f}; per hole "
          f"pixel cv2 {res['cv2_us_per_hole_px_median']:.2f} us, numba {res['numba_us_per_hole_px_median']:.2f} us; "
          f"outputs {'all equal' if res['all_equal'] else 'DIFFER'}")


# ---- --calls: per-function cost inside frames vs alone ---------------------------------------

CALL_TARGETS = (
    # (module or class path, attribute, label): looked up where the render loop calls them
    ("presim.synthesis.renderer", "check_rigid", "check_rigid"),
    ("presim.synthesis.renderer.Renderer", "select", "Renderer.select"),
    ("presim.synthesis.grids.FrameGrids", "next_view", "FrameGrids.next_view"),
    ("presim.synthesis.pipeline", "analyse_hole_mask", "analyse_hole_mask"),
    ("presim.synthesis.pipeline", "merge_into_holes", "merge_into_holes"),
    ("presim.synthesis.pipeline", "warp_layers", "warp_layers"),
    ("presim.synthesis.pipeline", "filtered_composite_banded", "filtered_composite_banded"),
    ("presim.synthesis.pipeline", "fill_holes", "fill_holes"),
)


def _resolve(path: str):
    import importlib

    parts = path.split(".")
    for k in range(len(parts), 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:k]))
        except ImportError:
            continue
        for p in parts[k:]:
            obj = getattr(obj, p)
        return obj
    raise ImportError(path)


def _copied(x):
    """``x`` with its numpy arrays copied (in tuples, lists and dicts too); other objects as they are."""
    if isinstance(x, np.ndarray):
        return x.copy()
    if isinstance(x, (tuple, list)):
        return type(x)(_copied(v) for v in x)
    if isinstance(x, dict):
        return {key: _copied(v) for key, v in x.items()}
    return x


def frame_calls(scene, K, poses: np.ndarray, perf, passes: int, repeats: int) -> dict:
    """Per wrapped function: calls per frame, mean us per call inside frames, mean of the medians of
    each call of one extra pass repeated alone (its array arguments copied)."""
    from presim.synthesis.renderer import RenderConfig, Renderer

    total: dict[str, float] = {}
    calls: dict[str, int] = {}
    last: dict[str, list] = {}
    mode = ["off"]  # "time": measured frames; "capture": keep every call's arguments
    undo = []

    def wrap(owner, name: str, label: str) -> None:
        fn = getattr(owner, name)

        def timed(*a, **k):
            if mode[0] == "capture":
                last.setdefault(label, []).append((fn, _copied(a), _copied(k)))
            if mode[0] != "time":
                return fn(*a, **k)
            t = time.perf_counter()
            out = fn(*a, **k)
            total[label] = total.get(label, 0.0) + time.perf_counter() - t
            calls[label] = calls.get(label, 0) + 1
            return out

        setattr(owner, name, timed)
        undo.append((owner, name, fn))

    for path, attr, label in CALL_TARGETS:
        owner = _resolve(path)
        if hasattr(owner, attr):
            wrap(owner, attr, label)
        else:
            print(f"note: {path}.{attr} not found, not measured", file=sys.stderr)
    try:
        r = Renderer(scene, RenderConfig(), perf)
        for _ in range(3):  # views prepared, kernels compiled
            for T in poses:
                r.render(T, K)
        n = 0
        mode[0] = "time"
        t0 = time.perf_counter()
        for _ in range(passes):
            for T in poses:
                r.render(T, K)
                n += 1
        frame_ms = (time.perf_counter() - t0) / n * 1e3
        mode[0] = "capture"
        for T in poses:
            r.render(T, K)
        mode[0] = "off"
        r.close()
    finally:
        for owner, name, fn in undo:
            setattr(owner, name, fn)
    res = {}
    for label in (t[2] for t in CALL_TARGETS):
        if label not in calls:
            continue
        alone_each = []
        for fn, a, k in last.get(label, []):  # every call of the capture pass, each repeated alone
            fn(*_copied(a), **_copied(k))  # warm-up: a copy may compile a new specialisation (layout)
            hot = []
            for _ in range(repeats):
                a2, k2 = _copied(a), _copied(k)  # (a call may write into its array arguments)
                t = time.perf_counter()
                fn(*a2, **k2)
                hot.append(time.perf_counter() - t)
            alone_each.append(statistics.median(hot))
        inside = total[label] / calls[label] * 1e6
        alone = statistics.fmean(alone_each) * 1e6 if alone_each else float("nan")
        res[label] = {"calls_per_frame": calls[label] / n, "us_in_frames": inside, "us_alone": alone,
                      "ratio": common.ratio(inside, alone)}
    return {"frame_ms_with_timers": frame_ms, "frames": n, "functions": res}


def _print_calls(name: str, size: str, res: dict) -> None:
    print(f"{name} {size}: {res['frames']} frames, {res['frame_ms_with_timers']:.3f} ms per frame (with the timers)")
    print(f"  {'function':28s} {'calls/frame':>11s} {'in frames us':>13s} {'alone us':>9s} {'ratio':>6s}")
    for label, v in res["functions"].items():
        print(f"  {label:28s} {v['calls_per_frame']:11.2f} {v['us_in_frames']:13.1f} {v['us_alone']:9.1f} "
              f"{v['ratio']:6.2f}")


# ---- main --------------------------------------------------------------------------------------

def load_scenes(args) -> dict:
    """name -> decoded Scene: ``--scene`` (named by its folder), else the synthetic room and (unless
    ``--quick``) the apc capture."""
    if args.scene:
        from presim.capture.store import load_scene

        return {Path(args.scene).name: load_scene(args.scene)}
    scenes = {"synthetic-room": common.synthetic_room()[0]}
    if not args.quick:
        apc = common.apc_capture()
        if apc is not None:
            scenes["apc-kinfu50 (raw depth)"] = apc
    return scenes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 epilog=__doc__.split("\n\n", 1)[1], formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", help="saved scene folder (default: synthetic room + apc capture)")
    ap.add_argument("--frames", type=int, default=30, help="measured frames per case")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--sizes", default="640x480,1280x720")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--passes", type=int, default=2, help="measured passes per config (alternating)")
    ap.add_argument("--no-today", action="store_true",
                    help="skip the same-run pass with lod_levels=0 and no selection reuse")
    ap.add_argument("--backend", default=None, help="PerfConfig.backend (numba, torch, reference)")
    ap.add_argument("--device", default=None, help="PerfConfig.torch_device (with --backend torch)")
    ap.add_argument("--threads", type=int, default=None, help="PerfConfig.threads (0 = all)")
    mode = ap.add_mutually_exclusive_group()
    mode.add_argument("--compare-blend", action="store_true",
                      help="time blending + sharpness + photometric correction against the default, same run")
    mode.add_argument("--fill", action="store_true", help="time the Telea fill kernel against cv2.inpaint")
    mode.add_argument("--calls", action="store_true", help="per-function cost inside frames vs alone")
    ap.add_argument("--repeats", type=int, default=7, help="--fill / --calls: repeats of each timed call")
    ap.add_argument("--max-hole-frac", type=float, default=0.02, help="--fill: frames with more holes are skipped")
    ap.add_argument("--quick", action="store_true",
                    help="smoke run: synthetic room only (unless --scene), 64x48, 3 frames, 1 pass, no today")
    args = ap.parse_args(argv)
    if args.quick:
        args.frames, args.warmup, args.passes, args.no_today, args.repeats = 3, 1, 1, True, 1
        args.sizes = "64x48"
    if min(args.frames, args.passes) < 1 or args.warmup < 0:
        ap.error("--frames and --passes must be >= 1, --warmup >= 0")
    sizes = common.parse_sizes(args.sizes)
    common.setup()
    from presim.synthesis.renderer import PerfConfig, RenderConfig

    perf_kw = {k: v for k, v in (("backend", args.backend), ("torch_device", args.device),
                                 ("threads", args.threads)) if v is not None}
    perf = PerfConfig(**perf_kw)
    common.header(perf=perf_kw or "default")
    results = {}
    bad = False
    for name, scene in load_scenes(args).items():
        poses = common.trajectory(scene, args.frames)
        for w, h in sizes:
            size = f"{w}x{h}"
            K = common.intrinsics_like(scene, w, h)
            if args.compare_blend:
                res = compare_blend(scene, K, poses, args.warmup, perf, args.passes)
                _print_blend(name, size, res, len(scene))
            elif args.fill:
                res = compare_fill(scene, K, poses, perf, args.repeats, args.max_hole_frac)
                _print_fill(name, size, res)
                bad |= not res["all_equal"]
            elif args.calls:
                res = frame_calls(scene, K, poses, perf, args.passes, args.repeats)
                _print_calls(name, size, res)
            else:
                today = None if args.no_today else RenderConfig(lod_levels=0, reuse_move_m=0.0)
                res = bench(scene, K, poses, args.warmup, RenderConfig(), perf, today, args.passes)
                _print_speed(name, size, res)
            results[f"{name} {size}"] = res
    peak_mb = common.peak_rss_mb()
    print(f"peak RSS: {peak_mb:.0f} MB")
    common.write_json(args.json, {"results": results, "peak_rss_mb": peak_mb, "perf": perf_kw,
                                  "load_average_end": os.getloadavg()})
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
