"""Teleop page in headless Chromium: camera frames/s drawn on the page, key-to-motion latency and the
server's memory, on a scene at 640x480 (the simulator steps in real time, dt 0.1 s, camera 10 Hz).

Baseline measured in the same run: the simulator's own steps/s (what the page could show at most).
Key-to-motion = keydown in the page -> the first frame drawn on the page whose step applied that key's
command (the page's own clock). RSS = this process (server + simulator + renderer; Chromium apart).

    .venv/bin/python benchmarks/bench_teleop.py [--scene DIR] [--seconds 10] [--taps 8] [--screenshot PNG]

Without ``--scene`` the built-in sample scene (seed 0, 640x480, 30 frames) is built into the temp folder.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import presim.runtime  # noqa: E402
presim.runtime.configure()  # process settings the timings depend on (presim/runtime.py)


def _scene(path: str | None) -> Path:
    if path:
        return Path(path)
    from presim.capture.sample_scene import SampleSceneConfig, build_sample_scene

    dst = Path(tempfile.gettempdir()) / "presim_bench_teleop_sample"
    if not (dst / "scene.json").exists():
        build_sample_scene(dst, seed=0, config=SampleSceneConfig(num_frames=30))
    return dst


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default=None)
    ap.add_argument("--seconds", type=float, default=10.0, help="driving time for the frames/s figure")
    ap.add_argument("--taps", type=int, default=8, help="key taps for the latency figure")
    ap.add_argument("--screenshot", type=Path, default=None, help="save a screenshot of the page here")
    args = ap.parse_args()

    import psutil

    from presim.cli import build_parser
    from presim.cli.teleop_cmd import build_simulator, make_recorder
    from presim.testing.browser import Browser, save_png
    from presim.outputs.teleop.server import TeleopServer
    from presim.outputs.teleop.session import TeleopConfig, TeleopSession

    scene = _scene(args.scene)
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
