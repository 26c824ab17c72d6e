"""Output costs: the sinks a simulation step feeds, and the teleop page in a browser.

Sub-commands:

- ``sinks``: per sink, synchronous (what its worker thread spends per step): mcap, capture folder,
  rrd, and the ROS 1 publisher when rospy + roscore are installed (a roscore on a free 127.0.0.1
  port, one process-local subscriber so messages are really serialised); what the step loop pays
  for the queued ``on_step`` hand-off with all sinks; steps/s of (a) a synthetic loop (precomputed
  steps, no rendering: the sinks' throughput limit; drops reported) and (b) the real simulator in the
  toy room with no sinks vs all sinks, measured in the same run. Medians over repeats after a warm-up.
  ``--compare-mcap`` adds MCAP chunk compressions (ms and MiB per step).
- ``teleop``: the teleop page in headless Chromium on a scene at 640x480 (the simulator steps in real
  time, dt 0.1 s, camera 10 Hz): camera frames/s drawn on the page against the simulator's own
  steps/s (the baseline: what the page could show at most), key-to-motion latency (keydown in the
  page -> the first frame drawn whose step applied that key's command, the page's own clock), the
  frame lag and the server's memory with one and two tabs. Needs Chromium and its driver.

    python benchmarks/bench_outputs.py sinks [--steps 40] [--repeats 3] [--width 640 --height 480] [--no-sim] [--no-ros]
    python benchmarks/bench_outputs.py sinks --quick                 # smoke run
    python benchmarks/bench_outputs.py teleop [--scene DIR] [--seconds 10] [--taps 8] [--screenshot PNG]
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
from benchmarks import common  # noqa: E402


# ---- sinks -------------------------------------------------------------------------------------

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
    from presim.outputs.queue import QueuedSink

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
    from presim.outputs.queue import QueuedSink
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


def cmd_sinks(args) -> dict:
    from presim.outputs.folder_recorder import FolderRecorder
    from presim.outputs.mcap_recorder import McapRecorder
    from presim.outputs.viewer import RerunViewer
    from presim.testing.steps import synthetic_info, synthetic_steps

    res: dict = {"per_sink_ms": {}}

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
            ms = res["per_sink_ms"][name] = per_sink_ms(make, info, steps, args.repeats)
            print(f"{name:<16}{ms:>18.2f}")

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
        res["synthetic_loop"] = {"none_steps_per_s": none_rate, "all_sinks_steps_per_s": all_rate,
                                 "handoff_ms_per_step": call_ms, "drops": drops}
        print(f"\nsynthetic loop (no rendering): none {none_rate:,.0f} steps/s | all sinks {all_rate:.1f} steps/s "
              f"(incl. draining at close) | loop pays {call_ms * 1e3:.0f} us/step for the hand-off | "
              f"drops {drops}")
        if not args.no_sim:
            base, allr = sim_loop(list(makes.values()), args.width, args.height, args.steps, args.repeats)
            res["simulator_loop"] = {"none_steps_per_s": base, "all_sinks_steps_per_s": allr, "ratio": allr / base}
            print(f"simulator loop (toy room, render every step): none {base:.2f} steps/s | all sinks "
                  f"{allr:.2f} steps/s | ratio {allr / base:.2f}")
    finally:
        if ros is not None:
            ros[1]()  # stop our roscore even when a measurement failed
        shutil.rmtree(tmp, ignore_errors=True)
    return res


# ---- teleop page ------------------------------------------------------------------------------

def cmd_teleop(args) -> dict:
    import psutil

    from presim.cli import build_parser
    from presim.cli.teleop_cmd import build_simulator, make_recorder
    from presim.testing.browser import Browser, save_png
    from presim.outputs.teleop.server import TeleopServer
    from presim.outputs.teleop.session import TeleopConfig, TeleopSession

    scene = args.scene or str(common.sample_scene(frames=30))
    targs = build_parser().parse_args(["teleop", str(scene)])
    out = Path(tempfile.mkdtemp(prefix="presim-bench-teleop-"))
    server = TeleopServer(TeleopSession(build_simulator(targs), TeleopConfig(out_dir=out), make_recorder))
    url = server.start()
    rss = psutil.Process().memory_info().rss / 2**20
    try:
        with Browser(1280, 1000) as b:
            b.open(url)
            deadline = time.monotonic() + 60
            while not b.execute("return window.teleop && window.teleop.framesDrawn >= 1"):
                if time.monotonic() > deadline:
                    raise TimeoutError("the page drew no frames in 60 s")
                time.sleep(0.2)
            # frames/s while driving (forward with turns: the image changes every frame)
            n0, s0 = b.execute("return window.teleop.framesDrawn"), server.session.latest.state["step"]
            t0 = time.perf_counter()
            k = 0
            while time.perf_counter() - t0 < args.seconds:
                b.keys("w" if k % 3 else "a", 0.7)
                k += 1
            wall = time.perf_counter() - t0
            n1, s1 = b.execute("return window.teleop.framesDrawn"), server.session.latest.state["step"]
            state = server.session.latest.state
            rss = max(rss, psutil.Process().memory_info().rss / 2**20)
            # key-to-motion: separate taps, the robot at rest before each
            b.execute("window.teleop.latencies = []")
            for i in range(args.taps):
                time.sleep(1.0)
                b.keys("d" if i % 2 else "a", 0.3)
            time.sleep(1.0)
            lat = b.execute("return window.teleop.latencies")
            lags = b.execute("return window.teleop.lags.slice(3)")
            # a second tab: both see, memory with two clients
            first = b.handles()[0]
            b.new_tab()
            b.open(url)
            time.sleep(3.0)
            two = b.execute("return window.teleop.framesDrawn")
            rss2 = psutil.Process().memory_info().rss / 2**20
            b.close_tab()
            b.switch_to(first)
            if args.screenshot is not None:   # turn towards the room, drive a little
                b.keys("a", 2.0)
                b.keys("w", 1.5)
                time.sleep(0.5)
                save_png(args.screenshot, b.screenshot())
    finally:
        server.stop()
    print(f"scene {scene}  camera {targs.width}x{targs.height}  dt {targs.dt} s")
    print(f"page frames/s while driving: {(n1 - n0) / wall:.2f}  (simulator {(s1 - s0) / wall:.2f} steps/s; "
          f"render {state['render_ms']:.0f} ms; ratio page/sim {(n1 - n0) / max(s1 - s0, 1):.2f})")
    if lat:
        print(f"key-to-motion latency: median {statistics.median(lat):.0f} ms, max {max(lat):.0f} ms over {len(lat)} taps")
    else:
        print("key-to-motion latency: no tap produced motion")
    if lags:
        print(f"frame lag (published -> drawn on the page): median {statistics.median(lags):.0f} ms, "
              f"max {max(lags):.0f} ms over {len(lags)} frames")
    print(f"server RSS: {rss:.0f} MiB with one tab, {rss2:.0f} MiB with two (second tab drew {two} frames in 3 s)")
    return {"scene": str(scene), "page_fps": (n1 - n0) / wall, "sim_steps_per_s": (s1 - s0) / wall,
            "key_to_motion_ms_median": statistics.median(lat) if lat else None,
            "frame_lag_ms_median": statistics.median(lags) if lags else None, "rss_mb_one_tab": rss,
            "rss_mb_two_tabs": rss2}


# ---- main --------------------------------------------------------------------------------------

def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("sinks", help="per-sink cost and steps/s with all sinks vs none")
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--no-sim", action="store_true", help="skip the real-simulator loop")
    p.add_argument("--no-ros", action="store_true")
    p.add_argument("--compare-mcap", action="store_true", help="also compare MCAP chunk compressions")
    p.add_argument("--quick", action="store_true", help="smoke run: 3 steps of 64x48, 1 repeat, no simulator, no ROS")
    p.add_argument("--json", help="write the results here")
    p = sub.add_parser("teleop", help="the teleop page in headless Chromium: frames/s, latency, memory")
    p.add_argument("--scene", default=None, help="saved scene (default: the sample scene, built once)")
    p.add_argument("--seconds", type=float, default=10.0, help="driving time for the frames/s figure")
    p.add_argument("--taps", type=int, default=8, help="key taps for the latency figure")
    p.add_argument("--screenshot", type=Path, default=None, help="save a screenshot of the page here")
    p.add_argument("--json", help="write the results here")
    args = ap.parse_args(argv)
    if getattr(args, "quick", False):
        args.steps, args.repeats, args.width, args.height, args.no_sim, args.no_ros = 3, 1, 64, 48, True, True
    common.setup()
    res = cmd_sinks(args) if args.cmd == "sinks" else cmd_teleop(args)
    common.write_json(args.json, {**res, "load_average_end": os.getloadavg()})
    return 0


if __name__ == "__main__":
    sys.exit(main())
