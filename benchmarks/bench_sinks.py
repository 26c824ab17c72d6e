"""Sink overhead: per-step cost of each sink and steps/s of the loop with all sinks vs none.

    .venv/bin/python benchmarks/bench_sinks.py [--steps 40] [--repeats 3] [--width 640 --height 480]
                                               [--no-sim] [--no-ros]

1. Per sink, synchronous (what its worker thread spends per step): mcap, capture folder, rrd, and the
   ROS 1 publisher when rospy + roscore are installed (a roscore on a free 127.0.0.1 port, one
   subscriber process-local so messages are really serialised).
2. What the step loop pays: the queued ``on_step`` call (drop-oldest hand-off) with all sinks.
3. steps/s of (a) a synthetic loop (precomputed 640x480 steps, no rendering: the sinks' throughput
   limit; drops are reported) and (b) the real simulator in the toy room, with no sinks vs all sinks,
   measured in the same run. Medians over repeats after a warm-up.
"""

from __future__ import annotations

import argparse
import itertools
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)
from presim.outputs.folder_recorder import FolderRecorder  # noqa: E402
from presim.outputs.mcap_recorder import McapRecorder  # noqa: E402
from presim.outputs.queue import QueuedSink  # noqa: E402
from presim.testing.steps import synthetic_info, synthetic_steps  # noqa: E402
from presim.outputs.viewer import RerunViewer  # noqa: E402


def _ros_setup(tmp: Path):
    """(make_sink, cleanup) or None when ROS 1 is not installed."""
    try:
        from presim.outputs.ros import (RosPublisherSink, import_rospy, ros_env, start_roscore,
                                        stop_process_group)
        from presim.outputs.viewer import free_port

        rospy = import_rospy()
        port = free_port()
        env = ros_env(port, base={k: v for k, v in os.environ.items() if not k.startswith("ROS_")}
                      | {"ROS_HOME": str(tmp / "ros")})
        core = start_roscore(port, env)
    except (ImportError, FileNotFoundError, RuntimeError) as e:
        print(f"(ros skipped: {e})")
        return None
    os.environ.update({k: env[k] for k in ("ROS_MASTER_URI", "ROS_IP", "ROS_HOSTNAME", "ROS_HOME")})
    rospy.init_node("bench_sinks", disable_signals=True)
    from sensor_msgs.msg import Image

    got = []
    rospy.Subscriber("/head_camera/color/image_raw", Image, lambda m: got.append(1), queue_size=2)

    def cleanup():
        rospy.signal_shutdown("bench done")
        stop_process_group(core)

    return (lambda d: RosPublisherSink()), cleanup


def per_sink_ms(make, info, steps, repeats: int) -> float:
    """Median over repeats of the mean synchronous on_step time (ms), after one warm-up pass."""
    runs = []
    for rep in range(repeats + 1):
        sink = make(rep)
        sink.open(info)
        t0 = time.perf_counter()
        for r in steps:
            sink.on_step(r)
        dt = (time.perf_counter() - t0) / len(steps) * 1e3
        sink.close()
        if rep > 0:
            runs.append(dt)
    return statistics.median(runs)


def synthetic_loop(makes, info, steps, repeats: int) -> tuple[float, float, int]:
    """(steps/s incl. draining at close, loop-side ms per on_step call, total drops)."""
    rates, call_ms, drops = [], [], 0
    for rep in range(repeats + 1):
        sinks = [QueuedSink(m(rep), f"s{i}", 64) for i, m in enumerate(makes)]
        for s in sinks:
            s.open(info)
        t0 = time.perf_counter()
        calls = 0.0
        for r in steps:
            tc = time.perf_counter()
            for s in sinks:
                s.on_step(r)
            calls += time.perf_counter() - tc
        for s in sinks:
            s.close()
        wall = time.perf_counter() - t0
        if rep > 0:
            rates.append(len(steps) / wall)
            call_ms.append(calls / len(steps) * 1e3)
            drops += sum(s.stats.dropped for s in sinks)
    return statistics.median(rates), statistics.median(call_ms), drops


def sim_loop(makes, width, height, n_steps, repeats) -> tuple[float, float]:
    """(steps/s with no sinks, steps/s with all sinks) of the real simulator; the two variants are
    interleaved per repeat so machine-load drift hits both alike."""
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator
    from presim.testing.toy_scene import build_toy_room

    scene = build_toy_room()
    cfg = SimConfig(dt_s=0.1, cameras=(CameraSpec(width=width, height=height, rate_hz=10.0),))
    rates: dict[bool, list[float]] = {False: [], True: []}
    for rep in range(repeats + 1):
        for with_sinks in (False, True):
            sim = Simulator(scene, config=cfg)
            if with_sinks:
                for i, m in enumerate(makes):
                    sim.add_sink(QueuedSink(m(100 + rep), f"s{i}", 64))
            sim.reset(seed=0, start=np.array([2.5, 2.0, np.pi]))
            for _ in range(3):  # the renderer fills its per-instance caches on the first renders
                sim.step(np.zeros(3))
            t0 = time.perf_counter()
            for k in range(n_steps):
                sim.step(np.array([0.2, 0.0, 0.3 if k % 20 < 10 else -0.3]))
            sim.close()  # drains the sinks: their cost is in the rate
            if rep > 0:
                rates[with_sinks].append(n_steps / (time.perf_counter() - t0))
    return statistics.median(rates[False]), statistics.median(rates[True])


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--no-sim", action="store_true", help="skip the real-simulator loop")
    ap.add_argument("--no-ros", action="store_true")
    ap.add_argument("--compare-mcap", action="store_true", help="also compare MCAP chunk compressions")
    args = ap.parse_args()
    os.environ.setdefault("PRESIM_NO_PROGRESS", "1")

    tmp = Path(tempfile.mkdtemp(prefix="bench_sinks_"))
    ros = None
    try:
        info = synthetic_info(num_points=100_000)
        steps = list(synthetic_steps(args.steps, width=args.width, height=args.height))
        uid = itertools.count()  # every sink instance writes to a fresh path
        makes = {
            "mcap": lambda i: McapRecorder(tmp / f"m{next(uid)}.mcap"),
            "capture folder": lambda i: FolderRecorder(tmp / f"cap{next(uid)}"),
            "rrd": lambda i: RerunViewer("rrd", tmp / f"v{next(uid)}.rrd"),
        }
        ros = None if args.no_ros else _ros_setup(tmp)
        if ros is not None:
            makes["ros1 publish"] = ros[0]
        print(f"sink overhead, {args.width}x{args.height} RGB-D every step, {args.steps} steps, "
              f"median of {args.repeats} (after warm-up)")
        print(f"{'sink':<16}{'ms/step (worker)':>18}")
        for name, make in makes.items():
            print(f"{name:<16}{per_sink_ms(make, info, steps, args.repeats):>18.2f}")

        if args.compare_mcap:
            from presim.outputs.mcap_recorder import McapConfig

            print("\nMCAP compression   ms/step   MiB/step")
            for comp in ("zstd", "lz4", "none"):
                paths = []

                def mk(i, comp=comp):
                    paths.append(tmp / f"c{next(uid)}.mcap")
                    return McapRecorder(paths[-1], McapConfig(compression=comp))

                ms = per_sink_ms(mk, info, steps, args.repeats)
                mib = paths[-1].stat().st_size / 2**20 / len(steps)
                print(f"{comp:<18}{ms:>8.2f}{mib:>11.3f}")

        none_rate = synthetic_loop([], info, steps, args.repeats)[0]
        all_rate, call_ms, drops = synthetic_loop(list(makes.values()), info, steps, args.repeats)
        print(f"\nsynthetic loop (no rendering): none {none_rate:,.0f} steps/s | all sinks {all_rate:.1f} steps/s "
              f"(incl. draining at close) | loop pays {call_ms * 1e3:.0f} us/step for the hand-off | "
              f"drops {drops}")
        if not args.no_sim:
            base, allr = sim_loop(list(makes.values()), args.width, args.height, args.steps, args.repeats)
            print(f"simulator loop (toy room, render every step): none {base:.2f} steps/s | all sinks "
                  f"{allr:.2f} steps/s | ratio {allr / base:.2f}")
    finally:
        if ros is not None:
            ros[1]()  # stop our roscore even when a measurement failed
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
