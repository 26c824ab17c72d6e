"""Steady-state rendering speed of the synthesis engine vs a naive numpy z-buffer, in one run.

For each scene and output size: a trajectory of novel poses (midpoints between consecutive captured
views, so every frame is a new pose near the capture) is rendered with the full pipeline
(``RenderConfig()``, numba), after a warm-up that compiles/loads what is needed. For every frame the
naive baseline (:func:`presim.synthesis.kernels_reference.naive_zbuffer_ref`: vectorized numpy
unproject -> project -> lexsort z-buffer of whole frames, no layers, no filtering, no fill) splats
the SAME views the pipeline used, so the ratio compares implementations, not view counts.
Steady state = the second pass over the trajectory (every view it needs already prepared and
cached); the first (cold) pass, which also reads and prepares views, is reported per frame too.

Each case is also measured with "today" = ``RenderConfig(lod_levels=0, reuse_move_m=0)`` (the
pipeline before level of detail and temporal reuse) in the same process, measured passes
alternating with the default config (``--passes``), reported as ``results[...]["today"]``,
``speedup_vs_today`` (wall) and ``cpu_speedup_vs_today``; ``--no-today`` skips it.
``--kernels-before`` adds, the same way, the default pipeline with the plain crack filter and
OpenCV's fill (``RenderConfig(packed_cracks=False, fill_kernel="opencv")``; the hole analysis has
no switch): ``results[...]["kernels_before"]`` and ``cpu_speedup_vs_kernels_before``.

Prints medians of wall ms/frame, frames/s, per-stage wall ms, views per frame, hole fraction, the
ratio baseline/pipeline, the CPU time per frame (process time summed over threads: on a machine
shared with other jobs it is the robust number; with NUMBA_NUM_THREADS=1 it equals the wall time
of an unloaded core), and the peak RSS of the process (numba's allocations bypass tracemalloc).

    .venv/bin/python benchmarks/bench_render.py                 # synthetic room + apc capture
    .venv/bin/python benchmarks/bench_render.py --scene out/sample --frames 40
    .venv/bin/python benchmarks/bench_render.py --scene out/apc --sizes 640x480,256x256,128x128 --json out/r.json
    .venv/bin/python benchmarks/bench_render.py --compare-blend     # + blending/colour correction cost
    .venv/bin/python benchmarks/bench_render.py --scene out/apc --sizes 128x128 --batch 8   # + render_batch

``--batch B`` also renders each case's poses with :meth:`Renderer.render_batch` in chunks of B poses
(frames spread over ``RenderConfig.batch_threads`` = auto threads, each frame on the serial twins of
the kernels) and, alternating pass by pass in the same run, the same chunks frame by frame with
:meth:`Renderer.render` (a second renderer, same config); both warm. Reported as
``results[...]["batch"]``: frames/s and wall / CPU ms per frame (medians over chunks) and the ratio
batch / frame by frame: the throughput of many poses at once (vector environments, datasets).

``--compare-blend`` instead renders every case with the default pipeline and with blending,
sharpness-aware views and photometric correction (``RenderConfig(blend=True, sharpness=True)`` on
the scene with a photometric calibration, matching frame 0's exposure), measured passes alternating
(base, blend, base, blend; ``--passes``), and prints the in-run ratio of the medians (blend / base,
wall and CPU) and both configs' per-stage medians (no naive baseline).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.capture.scene import ArrayFrameSource, Scene  # noqa: E402
from presim.geometry import Intrinsics, make_pose  # noqa: E402
from presim.testing import rect_scene as S  # noqa: E402
from presim.synthesis.kernels_reference import naive_zbuffer_ref  # noqa: E402
from presim.synthesis.renderer import STAGES, RenderConfig, Renderer  # noqa: E402

APC = ROOT.parent / "shared" / "data" / "apc_cardboard_bin_kinfu50"


def in_memory(scene: Scene) -> Scene:
    """The scene with all frames decoded into arrays (PNG decoding is not what we time)."""
    cols, deps = zip(*(scene.frames.load(i) for i in range(len(scene))))
    return dataclasses.replace(scene, frames=ArrayFrameSource(np.stack(cols), np.stack(deps)))


def load_scenes(args) -> dict[str, Scene]:
    scenes = {}
    if args.scene:
        from presim.capture.store import load_scene

        scenes[Path(args.scene).name] = load_scene(args.scene)
        return scenes
    K = Intrinsics.from_fov(640, 480, 60.0)
    scenes["synthetic-room"] = S.make_scene(S.room_rects(), S.orbit_poses(16, span_m=1.6), K)
    if APC.is_dir():
        from presim.capture.importers.kinfu import read

        scenes["apc-kinfu50 (raw depth)"] = in_memory(read(APC))
    else:
        print(f"note: {APC} not found, apc capture skipped", file=sys.stderr)
    return scenes


def trajectory(scene: Scene, n: int) -> np.ndarray:
    """``n`` novel poses: midpoints of consecutive captured views (cycled), rotation of the first."""
    T = scene.T_world_cam
    out = []
    for k in range(n):
        i = k % (len(T) - 1)
        out.append(make_pose(T[i][:3, :3], (T[i][:3, 3] + T[i + 1][:3, 3]) / 2))
    return np.stack(out)


def _measure(r: Renderer, K: Intrinsics, poses: np.ndarray, acc: dict) -> None:
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


def bench(scene: Scene, K: Intrinsics, poses: np.ndarray, warmup: int, config: RenderConfig,
          today: RenderConfig | None = None, passes: int = 2, kernels_before: RenderConfig | None = None) -> dict:
    """Steady-state numbers of ``config``; with ``today`` (and ``kernels_before``), the same for that
    config in the same run, measured passes alternating (config, today, config, today, ...) so load
    changes hit both."""
    rs = {"new": Renderer(scene, config)}
    if today is not None:
        rs["today"] = Renderer(scene, today)
    if kernels_before is not None:
        rs["kernels_before"] = Renderer(scene, kernels_before)
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
    res.update({"cache_mb": r.cache_bytes / 2**20, "cold_pass_ms_per_frame": cold["new"]})
    # The baseline in its own pass over the same poses and views (interleaving it with the
    # pipeline frame by frame evicted the pipeline's caches and parked its threads: +50 % per frame here).
    frames, base_ms, base_cpu = {}, [], []
    for T, vs in zip(poses, accs["new"]["used_views"]):
        used = []
        for v in vs:
            if v not in frames:
                frames[v] = scene.frames.load(v)
            used.append((*frames[v], scene.intrinsics[v], scene.T_world_cam[v]))
        t0, c0 = time.perf_counter(), time.process_time()
        naive_zbuffer_ref(used, T, K)
        base_ms.append((time.perf_counter() - t0) * 1e3)
        base_cpu.append((time.process_time() - c0) * 1e3)
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
    if kernels_before is not None:
        kb = _summary(accs["kernels_before"])
        res["kernels_before"] = kb
        res["speedup_vs_kernels_before"] = kb["ms_median"] / res["ms_median"]
        res["cpu_speedup_vs_kernels_before"] = kb["cpu_ms_median"] / res["cpu_ms_median"]
    return res


def compare_blend(name: str, size: str, scene: Scene, K: Intrinsics, poses: np.ndarray, warmup: int,
                  results: dict, passes: int = 2) -> None:
    """Default pipeline vs blending + sharpness + photometric correction, in one process: a cold
    pass and a warm-up per config, then measured passes alternating (base, blend, base, blend, ...)
    so load changes hit both; prints the ratio of the medians (blend / base), wall and CPU."""
    from presim.photometric import calibrate_photometric

    t0 = time.perf_counter()
    calib = calibrate_photometric(scene, show_progress=False)
    calib_s = time.perf_counter() - t0
    photo_scene = dataclasses.replace(scene, photometric=calib)
    rs = {"base": Renderer(scene, RenderConfig()),
          "blend": Renderer(photo_scene, RenderConfig(blend=True, sharpness=True, exposure_frame=scene.frame_ids[0]))}
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
    blend_ms = sm["blend"]["stages_ms_median"]["blend"]
    results[f"{name} {size}"] = {"base_ms": med["base"], "blend_ms": med["blend"], "ratio_wall": med["blend"] / med["base"],
                                 "base_cpu_ms": cpu["base"], "blend_cpu_ms": cpu["blend"],
                                 "ratio_cpu": cpu["blend"] / cpu["base"], "blend_stage_ms": blend_ms,
                                 "stages_ms_median": {k: v["stages_ms_median"] for k, v in sm.items()},
                                 "views_mean": {k: v["views_mean"] for k, v in sm.items()},
                                 "photometric_calibration_s": calib_s, "frames": len(poses), "passes": passes}
    print(f"{name:26s} {size:9s} base {med['base']:7.1f} ms  blend+sharp+photo {med['blend']:7.1f} ms  "
          f"ratio {med['blend'] / med['base']:.3f} (CPU {cpu['base']:.1f} -> {cpu['blend']:.1f} ms, "
          f"ratio {cpu['blend'] / cpu['base']:.3f})  blend stage {blend_ms:.1f} ms  "
          f"calibration {calib_s:.1f} s for {len(scene)} frames")
    for k, v in sm.items():
        print(f"{'':26s} {k:9s} views {v['views_mean']:.2f} | " + " ".join(
            f"{s}={x:.1f}" for s, x in v["stages_ms_median"].items() if x > 0))


def bench_batch(scene: Scene, K: Intrinsics, poses: np.ndarray, batch: int, passes: int = 2) -> dict:
    """``render_batch`` in chunks of ``batch`` poses against the same chunks rendered frame by frame
    (another renderer, same config), both warm, passes alternating; medians per chunk."""
    rs = {"batch": Renderer(scene, RenderConfig()), "single": Renderer(scene, RenderConfig())}
    chunks = [poses[a:a + batch] for a in range(0, len(poses), batch)]

    def run(name: str, acc: dict | None) -> None:
        for c in chunks:
            t0, c0 = time.perf_counter(), time.process_time()
            if name == "batch":
                rs[name].render_batch(c, K)
            else:
                for T in c:
                    rs[name].render(T, K)
            if acc is not None:
                acc[name]["ms"].append((time.perf_counter() - t0) * 1e3 / len(c))
                acc[name]["cpu"].append((time.process_time() - c0) * 1e3 / len(c))

    for name in rs:  # cold pass (prepares the views), then one warm pass
        run(name, None)
        run(name, None)
    acc = {name: {"ms": [], "cpu": []} for name in rs}
    for p in range(passes):
        for name in (("batch", "single") if p % 2 == 0 else ("single", "batch")):
            run(name, acc)
    med = {name: float(np.median(a["ms"])) for name, a in acc.items()}
    return {"batch": batch, "threads": rs["batch"].batch_threads(batch), "fps_median": 1e3 / med["batch"],
            "ms_per_frame_median": med["batch"], "cpu_ms_per_frame_median": float(np.median(acc["batch"]["cpu"])),
            "single_fps_median": 1e3 / med["single"], "single_ms_per_frame_median": med["single"],
            "single_cpu_ms_per_frame_median": float(np.median(acc["single"]["cpu"])),
            "speedup_vs_single": med["single"] / med["batch"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", help="saved scene folder (default: synthetic room + apc capture)")
    ap.add_argument("--frames", type=int, default=30, help="measured frames per case")
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--sizes", default="640x480,1280x720")
    ap.add_argument("--json", help="write the results here")
    ap.add_argument("--passes", type=int, default=2, help="measured passes per config (alternating)")
    ap.add_argument("--no-today", action="store_true",
                    help="skip the same-run pass with the pre-LOD pipeline (lod_levels=0, no selection reuse)")
    ap.add_argument("--kernels-before", action="store_true",
                    help="also time the default pipeline with the plain crack filter and OpenCV fill, same run")
    ap.add_argument("--batch", type=int, default=0,
                    help="also time render_batch in chunks of this many poses against frame by frame, same run")
    ap.add_argument("--compare-blend", action="store_true",
                    help="also time blending + sharpness + photometric correction against the default, same run")
    args = ap.parse_args()
    import numba

    print(f"numba threads: {numba.get_num_threads()}  load average at start: {os.getloadavg()}")
    results = {}
    for name, scene in load_scenes(args).items():
        hfov = scene.intrinsics[0].hfov_deg
        poses = trajectory(scene, args.frames)
        for size in args.sizes.split(","):
            w, h = (int(x) for x in size.split("x"))
            K = Intrinsics.from_fov(w, h, hfov)
            if args.compare_blend:
                compare_blend(name, size, scene, K, poses, args.warmup, results, args.passes)
                continue
            # "today": the pipeline before level of detail and temporal reuse, same run, same poses.
            today = None if args.no_today else RenderConfig(lod_levels=0, reuse_move_m=0.0)
            kb = RenderConfig(packed_cracks=False, fill_kernel="opencv") if args.kernels_before else None
            res = bench(scene, K, poses, args.warmup, RenderConfig(), today, args.passes, kb)
            results[f"{name} {size}"] = res
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
            if "kernels_before" in res:
                kb = res["kernels_before"]
                print(f"{'':26s} {'':9s} kernels before (packed_cracks=False, fill_kernel=opencv) {kb['ms_median']:7.1f} ms "
                      f"{kb['fps_median']:5.1f} fps  CPU {kb['cpu_ms_median']:7.1f} ms  -> wall "
                      f"x{res['speedup_vs_kernels_before']:.2f}  CPU x{res['cpu_speedup_vs_kernels_before']:.2f}  | " + " ".join(
                          f"{k}={v:.1f}" for k, v in kb["stages_ms_median"].items() if v > 0))
            if args.batch > 0:
                b = res["batch"] = bench_batch(scene, K, poses, args.batch, args.passes)
                print(f"{'':26s} {'':9s} render_batch of {b['batch']} on {b['threads']} threads: "
                      f"{b['ms_per_frame_median']:7.2f} ms/frame {b['fps_median']:6.1f} fps  CPU "
                      f"{b['cpu_ms_per_frame_median']:.2f} ms  | frame by frame {b['single_ms_per_frame_median']:.2f} ms "
                      f"{b['single_fps_median']:.1f} fps  -> x{b['speedup_vs_single']:.2f}")
    peak_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak RSS: {peak_mb:.0f} MB")
    if args.json:
        Path(args.json).write_text(json.dumps({"results": results, "peak_rss_mb": peak_mb,
                                               "load_average_end": os.getloadavg()}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
