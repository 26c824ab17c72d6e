"""``presim teleop``: the page's protocol is validated (pure functions), the map and depth colours
have known answers, the WebSocket server serves two tabs at once (one drives, both see), frees a
closed tab, refuses bad input without crashing, records like ``drive --record``, binds 127.0.0.1; a
real headless Chromium drives the robot with keys and sees the camera image change."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from presim.outputs.teleop.frames import colorize_depth, depth_range_m, hole_fraction, top_down_map
from presim.outputs.teleop.protocol import (CmdVel, JointTarget, ProtocolError, ProtocolSpec, Record, Simple,
                                            Teleport, parse_message)

SPEC = ProtocolSpec((-1.0, -2.0), (4.0, 3.0), {"head_tilt_joint": (-0.6, 0.9), "wheel": (-np.inf, np.inf)})


# ---- protocol (pure) -------------------------------------------------------------------------------
def test_valid_messages_parse():
    assert parse_message('{"type":"cmd_vel","vx":0.5,"vy":0,"wz":-1,"seq":7}', SPEC) == CmdVel(0.5, 0.0, -1.0, 0.0, 7)
    assert parse_message(b'{"type":"joint","name":"head_tilt_joint","value":0.2}', SPEC) == JointTarget("head_tilt_joint", 0.2)
    assert parse_message('{"type":"joint","name":"wheel","value":100}', SPEC) == JointTarget("wheel", 100.0)
    assert parse_message('{"type":"teleport","x":4.0,"y":-2.0}', SPEC) == Teleport(4.0, -2.0, None)
    assert parse_message('{"type":"teleport","x":0,"y":0,"yaw":1.5}', SPEC) == Teleport(0.0, 0.0, 1.5)
    assert parse_message('{"type":"record","on":true}', SPEC) == Record(True)
    for t in ("reset", "snapshot", "take_control"):
        assert parse_message(json.dumps({"type": t}), SPEC) == Simple(t)


@pytest.mark.parametrize("raw, reason", [
    ('{"type":"cmd_vel","vx":NaN,"vy":0,"wz":0}', "finite"),           # Python's json reads NaN literals
    ('{"type":"cmd_vel","vx":Infinity,"vy":0,"wz":0}', "finite"),
    ('{"type":"cmd_vel","vx":null,"vy":0,"wz":0}', "missing"),         # JSON.stringify(NaN) is null
    ('{"type":"cmd_vel","vx":"1","vy":0,"wz":0}', "number"),
    ('{"type":"cmd_vel","vx":true,"vy":0,"wz":0}', "number"),
    ('{"type":"cmd_vel","vx":0,"vy":0}', "missing"),
    ('{"type":"cmd_vel","vx":1e9,"vy":0,"wz":0}', "above"),
    ('{"type":"cmd_vel","vx":0,"vy":0,"wz":0,"seq":-1}', "integer"),
    ("not json {", "not JSON"),
    ("[1, 2]", "object"),
    ('{"vx": 1}', "unknown message type"),
    ('{"type":"fly"}', "unknown message type"),
    ('{"type":"teleport","x":4.01,"y":0}', "outside the map"),
    ('{"type":"teleport","x":0,"y":-2.5}', "outside the map"),
    ('{"type":"teleport","x":0}', "missing"),
    ('{"type":"joint","name":"head_tilt_joint","value":1.0}', "outside its limits"),
    ('{"type":"joint","name":"nope","value":0}', "unknown joint"),
    ('{"type":"record","on":"yes"}', "true or false"),
    ('{"type":"ack"}', "missing"),
    ('{"type":"reset","pad":"' + "x" * 5000 + '"}', "too long"),
    (b"\xff\xfe", "UTF-8"),
    ("[" * 100000, "too long"),
])
def test_bad_messages_are_refused_with_a_reason(raw, reason):
    with pytest.raises(ProtocolError, match=reason):
        parse_message(raw, SPEC)


def test_deeply_nested_json_is_refused_not_crashing():
    with pytest.raises(ProtocolError):
        parse_message("[" * 2000 + "]" * 2000, SPEC)


# ---- frames (known answers) ------------------------------------------------------------------------
def test_depth_colours_and_range():
    d = np.array([[0.0, 0.5, 4.0, 9.0]], np.float32)
    rgb = colorize_depth(d, 4.0)
    assert rgb.shape == (1, 4, 3) and rgb.dtype == np.uint8
    assert (rgb[0, 0] == 0).all()                      # invalid -> black
    assert (rgb[0, 2] == rgb[0, 3]).all()              # beyond the range clips to the far colour
    assert rgb[0, 1, 2] > rgb[0, 1, 0]                 # near is blue-ish on turbo
    assert rgb[0, 2, 0] > rgb[0, 2, 2]                 # far is red-ish
    assert depth_range_m(np.array([0.0, 1.2, 2.3], np.float32), percentile=100) == 2.5
    assert depth_range_m(np.zeros(3, np.float32)) == 5.0
    assert hole_fraction(np.array([True, True, False, True]), np.array([1.0, 0.0, 1.0, 1.0])) == 0.5


def test_top_down_map_places_points_and_obstacles():
    # 4 x 3 cells of 0.5 m from (0, 0); a red point in cell (row i=1, col j=2), an obstacle at (0, 3).
    occupied = np.zeros((3, 4), bool)
    occupied[0, 3] = True
    known = np.ones((3, 4), bool)
    known[2, 0] = False
    m = top_down_map(np.array([[1.2, 0.7, 0.3], [1.2, 0.7, 5.0]]), np.array([[255, 0, 0], [0, 0, 255]]),
                     occupied=occupied, known=known, origin_xy=(0.0, 0.0), resolution_m=0.5, z_max_m=2.0)
    assert m.rgb.shape == (3, 4, 3) and m.max_xy == (2.0, 1.5)
    # rows are flipped so +y is up: grid row i is image row H-1-i
    assert tuple(m.rgb[3 - 1 - 1, 2]) == (255, 0, 0)   # the point above z_max (blue) is left out
    assert m.rgb[3 - 1 - 0, 3, 0] > 100 and m.rgb[3 - 1 - 0, 3, 1] < 60   # obstacle tinted red
    assert tuple(m.rgb[0, 0]) == (70, 70, 70)          # unknown, no points: grey


# ---- the server over WebSockets (no browser) -------------------------------------------------------
@pytest.fixture
def toy_server(tmp_path):
    from presim.cli.teleop_cmd import make_recorder
    from presim.outputs.teleop.server import TeleopServer
    from presim.outputs.teleop.session import TeleopConfig, TeleopSession
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator
    from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

    sim = Simulator(build_toy_room(ToyRoomConfig(width=80, height=60)), None,
                    SimConfig(cameras=(CameraSpec(width=160, height=120),)))
    session = TeleopSession(sim, TeleopConfig(out_dir=tmp_path / "teleop"), make_recorder)
    server = TeleopServer(session)
    server.start()
    yield server
    server.stop()


class _Tab:
    """A minimal page: acks every frame, keeps the newest state and every info / error message."""

    def __init__(self, ws):
        self.ws, self.state, self.messages, self.images, self.init = ws, None, [], 0, None

    async def pump(self, seconds: float, until=None):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not (until and until(self)):
            try:
                m = await asyncio.wait_for(self.ws.recv(), timeout=max(0.01, end - time.monotonic()))
            except asyncio.TimeoutError:
                break
            if isinstance(m, bytes):
                if m[0] == 2:
                    self.images += 1
                    await self.ws.send(json.dumps({"type": "ack", "seq": self.state["seq"]}))
                continue
            d = json.loads(m)
            if d["type"] == "state":
                self.state = d
                if not d["has_images"]:
                    await self.ws.send(json.dumps({"type": "ack", "seq": d["seq"]}))
            elif d["type"] == "init":
                self.init = d
            elif d["type"] in ("info", "error"):
                self.messages.append((d["type"], d["message"]))

    async def send(self, **msg):
        await self.ws.send(json.dumps(msg))


def _ws_url(server) -> str:
    return f"ws://127.0.0.1:{server.port}/ws?token={server.token}"


def _connect(server, **kw):
    """A WebSocket as the server's own page opens it: its token, its Origin."""
    import websockets

    return websockets.connect(_ws_url(server), origin=f"http://127.0.0.1:{server.port}", **kw)


def test_two_tabs_one_drives_both_see_closed_tab_freed(toy_server):
    import websockets

    server, sim = toy_server, toy_server.session.sim

    async def main():
        async with _connect(server) as a, _connect(server) as b:
            ta, tb = _Tab(a), _Tab(b)
            await asyncio.gather(ta.pump(1.0), tb.pump(1.0))
            assert ta.init["client_id"] != tb.init["client_id"] and ta.images > 0 and tb.images > 0
            assert server.session.clients == {ta.init["client_id"], tb.init["client_id"]}
            p0 = sim.T_world_base[:3, 3].copy()
            assert ta.state["at_rest"] and tb.state["at_rest"]             # nothing to do: no steps, no renders
            step = server.session.latest.state["step"]
            await asyncio.gather(ta.pump(0.5), tb.pump(0.5))
            assert server.session.latest.state["step"] == step
            for k in range(8):   # tab A drives (first to send)
                await ta.send(type="cmd_vel", vx=0.5, vy=0, wz=0.4, seq=k)
                await asyncio.gather(ta.pump(0.1), tb.pump(0.1))
            assert np.linalg.norm(sim.T_world_base[:2, 3] - p0[:2]) > 0.05
            assert tb.state["driver"] == ta.init["client_id"]          # B sees A's drive
            assert abs(tb.state["pose"]["x"] - ta.state["pose"]["x"]) < 0.3
            await tb.send(type="cmd_vel", vx=0.5, vy=0, wz=0)             # B may not drive ...
            await tb.pump(0.5, until=lambda t: t.messages)
            assert tb.messages and "drives" in tb.messages[-1][1]
            await tb.send(type="take_control")                           # ... until it takes control
            await tb.pump(0.5)
            assert server.session.driver == tb.init["client_id"]
            await b.close()
            await ta.pump(0.5)
            assert server.session.clients == {ta.init["client_id"]} and len(server.clients) == 1
            assert server.session.driver is None                          # the closed tab released control
        for _ in range(50):
            if not server.clients:
                break
            await asyncio.sleep(0.05)
        assert not server.clients and not server.session.clients

    asyncio.run(main())
    step = server.session.latest.state["step"]
    time.sleep(0.5)
    assert server.session.latest.state["step"] == step               # no tab: the simulator pauses


def test_bad_input_refused_server_survives_recording_and_snapshot(toy_server, tmp_path):
    import urllib.request

    import websockets

    server, sim = toy_server, toy_server.session.sim

    async def main():
        async with _connect(server) as ws:
            t = _Tab(ws)
            await t.pump(0.5)
            for raw in ('{"type":"cmd_vel","vx":NaN,"vy":0,"wz":0}', "garbage", b"\x00\xff",
                        '{"type":"teleport","x":1000,"y":0}', '{"type":"cmd_vel","vx":null,"vy":0,"wz":0}'):
                await ws.send(raw)
            await t.pump(1.5, until=lambda t: len(t.messages) >= 5)
            errors = [m for k, m in t.messages if k == "error"]
            assert len(errors) == 5 and all(m.startswith("refused:") for m in errors)
            assert "outside the map" in errors[3]
            # teleport into the pillar of the toy room: valid JSON, inside the map, refused by the session
            await t.send(type="teleport", x=3.6, y=2.0)
            await t.pump(1.0, until=lambda t: len(t.messages) >= 6)
            assert "obstacle" in t.messages[-1][1]
            await t.send(type="teleport", x=1.0, y=1.0, yaw=0.0)
            await t.pump(1.0, until=lambda t: len(t.messages) >= 7)
            assert np.allclose(sim.T_world_base[:2, 3], [1.0, 1.0], atol=1e-6)
            await t.send(type="joint", name="head_tilt_joint", value=0.5)   # wakes a robot at rest
            await t.pump(1.0, until=lambda t: abs(t.state["joints"]["head_tilt_joint"] - 0.5) < 1e-6)
            assert abs(t.state["joints"]["head_tilt_joint"] - 0.5) < 1e-6
            await t.send(type="record", on=True)
            for k in range(10):
                await t.send(type="cmd_vel", vx=0.3, vy=0, wz=0.0, seq=k)
                await t.pump(0.1)
            await t.send(type="teleport", x=1.5, y=1.5)                  # refused while recording
            await t.send(type="snapshot")
            await t.send(type="record", on=False)
            await t.pump(3.0, until=lambda t: any("recording saved" in m for _, m in t.messages))
            async with _connect(server, max_size=None) as big:   # 100 kB: this tab is closed
                await big.send("x" * 100_000)
                with pytest.raises(websockets.ConnectionClosed):
                    for _ in range(100):
                        await asyncio.wait_for(big.recv(), 5)
            await t.pump(0.5)                                                   # the first tab carries on
            assert t.ws.state.name == "OPEN"
            return t

    t = asyncio.run(main())
    text = "\n".join(m for _, m in t.messages)
    assert "stop the recording before teleporting" in text and "snapshot saved" in text
    rec = tmp_path / "teleop" / "rec_000"
    assert (rec / "recording.mcap").stat().st_size > 0 and (rec / "capture").is_dir()
    assert list((tmp_path / "teleop" / "snapshots").glob("snap_000_depth.png"))
    assert abs(sim.joint_positions[sim.robot.joint_index("head_tilt_joint")] - 0.5) < 1e-6
    with urllib.request.urlopen(f"{server.base_url}health?token={server.token}", timeout=5) as f:   # still serving
        assert json.loads(f.read())["error"] is None


def test_free_rig_session_map_from_points_and_teleport_keeps_height(tmp_path):
    """A scene without a floor drives the free camera rig: the map comes from the points, teleport
    moves x, y and keeps height and orientation."""
    import dataclasses

    from presim.outputs.teleop.protocol import Teleport
    from presim.outputs.teleop.session import TeleopConfig, TeleopSession, _Command
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator
    from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

    scene = dataclasses.replace(build_toy_room(ToyRoomConfig(width=40, height=30)), floor=None)
    sim = Simulator(scene, None, SimConfig(cameras=(CameraSpec(width=40, height=30),)))
    assert sim.is_free
    session = TeleopSession(sim, TeleopConfig(out_dir=tmp_path))
    lo, hi = session.spec.map_min_xy, session.spec.map_max_xy
    assert lo[0] < 0.0 and hi[0] > 5.0 and lo[1] < 0.0 and hi[1] > 4.0   # the 5 x 4 m room + padding
    session.sim.reset(0)
    T0 = sim.T_world_base
    session._apply(_Command(1, Teleport(2.0, 1.5)))
    T1 = sim.T_world_base
    np.testing.assert_allclose(T1[:3, 3], [2.0, 1.5, T0[2, 3]], atol=1e-9)
    np.testing.assert_allclose(T1[:3, :3], T0[:3, :3], atol=1e-9)
    session.sim.close()


@pytest.mark.slow
def test_cli_teleop_serves_page_on_loopback_and_stops_on_sigterm(tmp_path):
    import signal
    import urllib.error
    import urllib.request

    import psutil

    from presim.capture.store import save_scene
    from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

    save_scene(build_toy_room(ToyRoomConfig(width=80, height=60)), tmp_path / "toy")
    p = subprocess.Popen([sys.executable, "-m", "presim", "teleop", str(tmp_path / "toy"), "--width", "160",
                          "--height", "120", "--record", str(tmp_path / "rec")],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = None
        deadline = time.monotonic() + 60
        while url is None and time.monotonic() < deadline:
            line = p.stdout.readline()
            if not line:
                break
            if "open http://" in line:
                url = line.split("open ")[1].split()[0]
        assert url and url.startswith("http://127.0.0.1:"), p.stderr.read() if p.poll() is not None else url
        base, _, query = url.partition("?")
        assert query.startswith("token=") and len(query) > 20           # a per-run token in the URL
        port = int(base.rstrip("/").rsplit(":", 1)[1])
        listen = {c.laddr.ip for c in psutil.Process(p.pid).net_connections(kind="inet")
                  if c.status == psutil.CONN_LISTEN}
        assert listen == {"127.0.0.1"}
        with urllib.request.urlopen(url, timeout=10) as f:
            page = f.read().decode()
        assert "/static/app.js" in page and "http" not in page.replace("http-equiv", "")  # no CDN
        with urllib.request.urlopen(base + "static/app.js", timeout=10) as f:
            assert b"WebSocket" in f.read()
        with pytest.raises(urllib.error.HTTPError, match="403"):      # the page without the token
            urllib.request.urlopen(base, timeout=10)
        assert port > 0
        p.send_signal(signal.SIGTERM)
        assert p.wait(30) == 0
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()


def test_cli_teleop_bad_port_is_one_line(tmp_path, capsys):
    from presim.cli import main

    assert main(["teleop", str(tmp_path / "missing")]) == 1
    assert "scene folder not found" in capsys.readouterr().err


def test_cli_teleop_render_budget_default_and_refusal(tmp_path, capsys):
    from presim.cli import build_parser, main

    assert build_parser().parse_args(["teleop", str(tmp_path)]).render_budget_ms == 80.0
    for bad in ("-1", "nan"):
        assert main(["teleop", str(tmp_path), "--render-budget-ms", bad]) == 1
        err = capsys.readouterr().err
        assert "--render-budget-ms must be >= 0" in err and len(err.strip().splitlines()) == 1


# ---- a real browser ---------------------------------------------------------------------------------
def _canvas_crop(browser, img: np.ndarray, element_id: str) -> np.ndarray:
    r = browser.execute(f"const r = document.getElementById('{element_id}').getBoundingClientRect();"
                        "return [r.left, r.top, r.width, r.height, window.devicePixelRatio];")
    x, y, w, h, dpr = (float(v) for v in r)
    return img[int(y * dpr):int((y + h) * dpr), int(x * dpr):int((x + w) * dpr)]


def _wait(browser, script: str, timeout_s: float = 20.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        v = browser.execute(script)
        if v:
            return v
        time.sleep(0.2)
    raise AssertionError(f"timed out waiting for: {script}")


@pytest.mark.slow
@pytest.mark.browser
def test_browser_keys_drive_robot_and_page_image_changes(toy_server, tmp_path):
    import psutil

    from presim.testing.browser import Browser, find_browser, save_png

    try:
        find_browser()
    except FileNotFoundError as e:
        if os.environ.get("CI") == "true":
            raise
        pytest.skip(str(e))
    server, sim = toy_server, toy_server.session.sim
    listen = {c.laddr.ip for c in psutil.Process().net_connections(kind="inet")
              if c.status == psutil.CONN_LISTEN and c.laddr.port == server.port}
    assert listen == {"127.0.0.1"}
    with Browser(1280, 900) as b:
        b.open(server.url)
        _wait(b, "return window.teleop && window.teleop.framesDrawn >= 1")
        before = _canvas_crop(b, b.screenshot(), "color")
        assert before.std() > 5, "colour canvas is blank"
        p0 = sim.T_world_base.copy()
        b.keys("w", 1.2)
        b.keys("\ue012", 0.8)   # arrow left: turn
        p1 = sim.T_world_base
        moved = np.linalg.norm(p1[:2, 3] - p0[:2, 3])
        turned = abs(np.arctan2(p1[1, 0], p1[0, 0]) - np.arctan2(p0[1, 0], p0[0, 0]))
        assert moved > 0.1 or turned > 0.2, f"robot did not move: {moved:.3f} m, {turned:.3f} rad"
        # the robot stops (keys up), the page shows its last image, the simulator pauses at rest
        _wait(b, "return window.teleop.lastState.at_rest && window.teleop.framesDrawn >= 2", 30)
        img = b.screenshot()
        save_png(tmp_path / "teleop_page.png", img)
        after = _canvas_crop(b, img, "color")
        diff = np.abs(after.astype(np.int16) - before.astype(np.int16)).mean()
        assert diff > 3, f"camera image on the page did not change (mean abs diff {diff:.2f})"
        lat = b.execute("return window.teleop.latencies")
        assert lat and min(lat) < 2000, lat
        # The page shows a refusal for bad input; the server keeps running.
        b.execute("""window.teleop.sendRaw('{"type":"cmd_vel","vx":NaN,"vy":0,"wz":0}')""")
        _wait(b, "const m = document.getElementById('msg');"
                 "return m.classList.contains('error') && m.textContent.includes('refused')")
        # A second tab sees the first one drive; closing it frees its client.
        first = b.handles()[0]
        b.new_tab()
        b.open(server.url)
        _wait(b, "return window.teleop && window.teleop.framesDrawn >= 1 && window.teleop.lastState")
        assert len(server.clients) == 2
        state = b.execute("return window.teleop.lastState")
        assert state["driver"] is not None and state["driver"] != b.execute("return window.teleop.clientId")
        b.close_tab()
        b.switch_to(first)
        deadline = time.monotonic() + 10
        while len(server.clients) != 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(server.clients) == 1 and len(server.session.clients) == 1


# ---- access: Host, Origin, token (issue 44 item 1) ------------------------------------------------
def _http_status(port: int, path: str, headers: dict[str, str], method: str = "GET") -> int:
    """Status of one raw HTTP/1.1 request to 127.0.0.1:port (the curl reproduction, without curl)."""
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall((f"{method} {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in headers.items())
                   + "Content-Length: 0\r\n\r\n").encode())
        return int(s.recv(4096).split()[1])


def _upgrade(host: str, origin: str | None) -> dict[str, str]:
    h = {"Host": host, "Connection": "Upgrade", "Upgrade": "websocket", "Sec-WebSocket-Version": "13",
         "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ=="}
    if origin is not None:
        h["Origin"] = origin
    return h


def test_access_policy_refusals_are_pure():
    from presim.outputs.teleop.access import AccessPolicy, refusal

    pol = AccessPolicy(8000, "tok")
    good = {"host": "127.0.0.1:8000", "origin": "http://127.0.0.1:8000"}

    def why(headers, query="token=tok", websocket=True, method="GET", path="/ws"):
        return refusal(pol, method=method, path=path, query=query, headers=headers, websocket=websocket)

    assert why(good) is None
    assert why({"host": "localhost:8000", "origin": "http://localhost:8000"}) is None
    assert why({"host": "[::1]:8000", "origin": "http://[::1]:8000"}) is None
    assert "Host" in why({"host": "evil.example", "origin": "http://evil.example"})
    assert "Host" in why({"host": "127.0.0.1:8001", "origin": "http://127.0.0.1:8000"})   # another port
    assert "Host" in why({"origin": "http://127.0.0.1:8000"})
    assert "Origin" in why({"host": "127.0.0.1:8000", "origin": "http://evil.example"})
    assert "Origin" in why({"host": "127.0.0.1:8000"})
    assert "token" in why(good, query="")
    assert "token" in why(good, query="token=tok2")
    assert why({"host": "127.0.0.1:8000"}, query="", websocket=False, path="/static/app.js") is None
    assert "token" in why({"host": "127.0.0.1:8000"}, query="", websocket=False, path="/")
    assert "method" in why(good, websocket=False, method="POST", path="/")
    wide = AccessPolicy(8000, "tok", allow_origins=("http://dev.example:9000",))
    assert refusal(wide, method="GET", path="/ws", query="token=tok", websocket=True,
                   headers={"host": "dev.example:9000", "origin": "http://dev.example:9000"}) is None
    anyone = AccessPolicy(8000, "tok", allow_origins=("*",))
    assert refusal(anyone, method="GET", path="/ws", query="token=tok", websocket=True,
                   headers={"host": "evil.example", "origin": "http://evil.example"}) is None
    assert "token" in refusal(anyone, method="GET", path="/ws", query="", websocket=True,
                              headers={"host": "evil.example", "origin": "http://evil.example"})


@pytest.mark.fuzz
def test_cross_site_and_rebinding_requests_get_403(toy_server):
    """Issue 44's reproduction: an upgrade with a foreign Origin / Host, or without the token, is 403;
    the page's own request is 101; nothing refused reaches the simulator."""
    server = toy_server
    port, tok = server.port, server.token
    own, local = f"127.0.0.1:{port}", f"http://127.0.0.1:{port}"
    cases = [
        ("/ws", _upgrade("evil.example", "http://evil.example"), 403),              # the curl
        (f"/ws?token={tok}", _upgrade("evil.example", "http://evil.example"), 403),  # DNS rebinding
        (f"/ws?token={tok}", _upgrade(own, "http://evil.example"), 403),            # cross-site page
        (f"/ws?token={tok}", _upgrade(own, None), 403),                             # no Origin
        ("/ws", _upgrade(own, local), 403),                                         # no token
        ("/ws?token=guess", _upgrade(own, local), 403),                             # wrong token
        (f"/ws?token={tok}", _upgrade(f"localhost:{port}", f"http://localhost:{port}"), 101),
        (f"/ws?token={tok}", _upgrade(own, local), 101),
    ]
    for path, headers, want in cases:
        assert _http_status(port, path, headers) == want, (path, headers)
    assert _http_status(port, "/", {"Host": own}) == 403
    assert _http_status(port, "/health", {"Host": own}) == 403
    assert _http_status(port, f"/?token={tok}", {"Host": own}) == 200
    assert _http_status(port, f"/?token={tok}", {"Host": "evil.example"}) == 403
    assert _http_status(port, f"/?token={tok}", {"Host": own, "Origin": local}, method="POST") == 403
    assert _http_status(port, "/static/app.js", {"Host": own}) == 200                # assets: no secret
    assert server.refused == 10
    assert server.session.driver is None


# ---- capture users: every degree of freedom, camera path as TUM (issue 45 item 5) -----------------
@pytest.fixture
def free_server(tmp_path):
    import dataclasses

    from presim.outputs.teleop.server import TeleopServer
    from presim.outputs.teleop.session import TeleopConfig, TeleopSession
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator
    from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

    scene = dataclasses.replace(build_toy_room(ToyRoomConfig(width=80, height=60)), floor=None)
    sim = Simulator(scene, None, SimConfig(cameras=(CameraSpec(width=80, height=60),)))
    server = TeleopServer(TeleopSession(sim, TeleopConfig(out_dir=tmp_path / "teleop")))
    server.start()
    yield server
    server.stop()


class _CaptureTab(_Tab):
    """A _Tab that also keeps ``pose`` and ``path_saved`` answers."""

    async def pump(self, seconds: float, until=None):
        end = time.monotonic() + seconds
        while time.monotonic() < end and not (until and until(self)):
            try:
                m = await asyncio.wait_for(self.ws.recv(), timeout=max(0.01, end - time.monotonic()))
            except asyncio.TimeoutError:
                break
            if isinstance(m, bytes):
                if m[0] == 2:
                    await self.ws.send(json.dumps({"type": "ack", "seq": self.state["seq"]}))
                continue
            d = json.loads(m)
            if d["type"] == "state":
                self.state = d
                if not d["has_images"]:
                    await self.ws.send(json.dumps({"type": "ack", "seq": d["seq"]}))
            elif d["type"] == "init":
                self.init = d
            elif d["type"] in ("info", "error"):
                self.messages.append((d["type"], d["message"]))
            else:
                self.messages.append((d["type"], d))


def test_free_rig_buttons_move_every_axis_and_camera_path_exports_tum(free_server, tmp_path):
    from presim.formats.tum import read_tum
    from presim.geometry import pose_from_tum

    server, session = free_server, free_server.session

    def answers(t, kind):
        return [m for k, m in t.messages if k == kind]

    async def main():
        async with _connect(server) as ws:
            t = _CaptureTab(ws)
            await t.pump(1.0, until=lambda t: t.init and t.state)
            assert t.init["free"] and t.init["dofs"] == ["vx", "vy", "vz", "wx", "wy", "wz"]
            assert len(t.init["captures"]) == len(session.sim.scene)                 # captured cameras
            z0, pitch0 = t.state["camera"]["z"], t.state["camera"]["pitch"]
            await t.send(type="path", action="start")
            for k in range(6):                                                     # R (up) + I (tilt down)
                await t.send(type="cmd_vel", vx=0, vy=0, wz=0, vz=0.3, wy=0.5, seq=k)
                await t.pump(0.1)
            await t.send(type="cmd_vel", vx=0, vy=0, wz=0, seq=99)
            await t.pump(10.0, until=lambda t: t.state["step"] > 2 and t.state["at_rest"])
            assert t.state["camera"]["z"] > z0 + 0.02 and t.state["camera"]["pitch"] > pitch0 + 0.05
            step = t.state["step"]
            await t.send(type="cmd_vel", vx=0, vy=0, wz=0, wx=0.5, seq=100)        # U (roll) moves too
            await t.pump(0.3)
            await t.send(type="cmd_vel", vx=0, vy=0, wz=0, seq=101)
            await t.pump(10.0, until=lambda t: t.state["step"] > step and t.state["at_rest"])
            await t.send(type="path", action="stop")
            await t.send(type="path", action="add")
            await t.send(type="pose")
            await t.pump(2.0, until=lambda t: answers(t, "pose"))
            await t.send(type="path", action="save")
            await t.pump(3.0, until=lambda t: answers(t, "path_saved"))
            await t.send(type="path", action="bogus")
            await t.pump(1.0, until=lambda t: any("'action' must be" in m for k, m in t.messages if k == "error"))
            return t

    t = asyncio.run(main())
    pose = answers(t, "pose")[0]
    T_now = session.T_world_cam()
    np.testing.assert_allclose(np.array(pose["T_world_cam"]), T_now, atol=1e-9)
    vals = [float(v) for v in pose["tum"].split()]
    np.testing.assert_allclose(pose_from_tum(vals[1:]), T_now, atol=1e-6)
    assert len(pose["pose_arg"].split()) == 7                                      # presim render --pose
    saved = answers(t, "path_saved")[0]
    path = tmp_path / "teleop" / "paths" / "path_000.tum"
    assert saved["path"] == str(path) and saved["tum"] == path.read_text()       # the download = the file
    stamps, poses = read_tum(path)                                                 # presim's one TUM reader
    assert len(poses) == saved["poses"] >= 8 and np.all(np.diff(stamps) > 0)
    np.testing.assert_allclose(poses[-1], T_now, atol=1e-6)                        # 'add' = the pose now
    assert np.ptp(poses[:, 2, 3]) > 0.02                                           # the path went up
    assert "'action' must be" in t.messages[-1][1]


def test_axes_a_robot_lacks_warn_once_per_tab(toy_server):
    server = toy_server

    async def main():
        async with _connect(server) as ws:
            t = _Tab(ws)
            await t.pump(0.5)
            assert t.init["dofs"] == ["vx", "wz"] and not t.init["free"]
            for k in range(3):
                await t.send(type="cmd_vel", vx=0.1, vy=0.3, wz=0, vz=0.2, seq=k)
                await t.pump(0.2)
            return t

    t = asyncio.run(main())
    infos = [m for k, m in t.messages if k == "info"]
    assert sum("'vy' is ignored" in m for m in infos) == 1 and sum("'vz' is ignored" in m for m in infos) == 1


def test_free_rig_tilt_applies_to_the_start_view(tmp_path):
    """``--tilt-deg`` on the free rig: 40 deg pitches the captured start view down by 40 deg, and the
    image differs from 0 deg (it used to be byte-identical)."""
    import dataclasses

    from presim.outputs.teleop.session import TeleopConfig, TeleopSession
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator
    from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

    scene = dataclasses.replace(build_toy_room(ToyRoomConfig(width=40, height=30)), floor=None)
    views = {}
    for deg in (0.0, 40.0):
        sim = Simulator(scene, None, SimConfig(cameras=(CameraSpec(width=40, height=30),)))
        session = TeleopSession(sim, TeleopConfig(out_dir=tmp_path, start_pitch_rad=np.radians(deg)))
        r = session._reset_start()
        views[deg] = (session.T_world_cam(), r.cameras[0].color)
        sim.close()
    (T0, c0), (T40, c40) = views[0.0], views[40.0]
    np.testing.assert_allclose(T40[:3, 3], T0[:3, 3], atol=1e-9)                   # same place ...
    angle = np.degrees(np.arccos(np.clip(T0[:3, 2] @ T40[:3, 2], -1, 1)))
    assert abs(angle - 40.0) < 1e-6                                                 # ... view 40 deg apart
    assert T40[:3, 2] @ T0[:3, 1] > 0                                               # towards camera +y: down
    assert not np.array_equal(c0, c40)


def test_cli_options_that_cannot_act_warn(tmp_path):
    import argparse

    from presim.cli.teleop_cmd import inactive_option_warnings
    from presim.sim.robot import default_robot, free_camera_rig

    ns = argparse.Namespace
    assert inactive_option_warnings(ns(drive=None, camera_link=None, tilt_deg=30.0), free_camera_rig()) == []
    w = inactive_option_warnings(ns(drive="holonomic", camera_link="x", tilt_deg=None), free_camera_rig())
    assert len(w) == 2 and "--drive holonomic" in w[0] and "--camera-link" in w[1]
    assert inactive_option_warnings(ns(drive="diff", camera_link=None, tilt_deg=20.0), default_robot()) == []


def test_free_rig_map_outlines_the_point_footprint():
    # a 1 x 1 m square of red points: its border cells are cyan, inside stays red, outside is dark
    g = np.stack(np.meshgrid(np.arange(0, 1.0, 0.01), np.arange(0, 1.0, 0.01)), -1).reshape(-1, 2)
    xyz = np.c_[g, np.zeros(len(g))]
    m = top_down_map(xyz, np.tile([255, 0, 0], (len(g), 1)), resolution_m=0.1, pad_m=0.3, footprint=True)
    h, w = m.rgb.shape[:2]
    assert (h, w) == (16, 16)
    assert tuple(m.rgb[h // 2, w // 2]) == (255, 0, 0)
    row = [tuple(int(v) for v in px) for px in m.rgb[h // 2]]
    inside = [j for j, px in enumerate(row) if px != (35, 35, 35)]
    assert len(inside) in (10, 11) and inside == list(range(inside[0], inside[-1] + 1))   # 1 m of 0.1 m cells
    assert row[inside[0]] == row[inside[-1]] == (0, 210, 230)
    assert all(px == (255, 0, 0) for px in row[inside[0] + 1:inside[-1]])
    assert tuple(m.rgb[0, 0]) == (35, 35, 35)


# ---- snapshot depth follows formats.depth_png (issue 41 item 6) ------------------------------------
def test_snapshot_depth_out_of_range_is_invalid_not_clipped(tmp_path):
    import types

    import cv2

    from presim.geometry import Intrinsics
    from presim.outputs.teleop.session import TeleopConfig, TeleopSession

    session = TeleopSession.__new__(TeleopSession)      # only what _snapshot reads
    session.config = TeleopConfig(out_dir=tmp_path)
    depth = np.array([[0.0, 1.2344, 70.0, np.inf]], np.float32)
    session._last_cam = types.SimpleNamespace(
        depth_m=depth, color=np.zeros((1, 4, 3), np.uint8), K=Intrinsics(2.0, 2.0, 2.0, 0.5, 4, 1),
        T_world_cam=np.eye(4), stamp_s=0.5)
    path, n_far = session._snapshot()
    png = cv2.imread(str(tmp_path / "snapshots" / "snap_000_depth.png"), cv2.IMREAD_UNCHANGED)
    assert png.dtype == np.uint16 and png.tolist() == [[0, 1234, 0, 0]] and n_far == 2
    meta = json.loads((tmp_path / "snapshots" / "snap_000.json").read_text())
    assert meta["n_depth_beyond_range"] == 2 and meta["depth_scale_m"] == 0.001


# ---- memory after a flood and 200 clients (issue 44 item 9) ----------------------------------------
_SERVER_CHILD = """
import sys
from presim.outputs.teleop.server import TeleopServer
from presim.outputs.teleop.session import TeleopConfig, TeleopSession
from presim.sensors.camera import CameraSpec
from presim.sim.simulator import SimConfig, Simulator
from presim.testing.toy_scene import ToyRoomConfig, build_toy_room
sim = Simulator(build_toy_room(ToyRoomConfig(width=80, height=60)), None,
                SimConfig(cameras=(CameraSpec(width=160, height=120),)))
s = TeleopServer(TeleopSession(sim, TeleopConfig(out_dir=sys.argv[1])))
s.start()
print(s.port, s.token, flush=True)
sys.stdin.read()
s.stop()
"""


@pytest.mark.fuzz
@pytest.mark.slow
def test_server_memory_stays_bounded_after_flood_and_200_clients(tmp_path):
    """The server (its own process) after a 5 000-message flood of bad input and 200 tabs that never
    read, while one tab turns the robot: at most 32 tabs are served, the rest told so; when they are
    gone the server's RSS is within 25 MB of where it started (measured 12 MB at 160x120 here)."""
    import psutil
    import websockets

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(__import__("pathlib").Path(__file__).parents[1]),
                                                       os.environ.get("PYTHONPATH", "")]))
    p = subprocess.Popen([sys.executable, "-c", _SERVER_CHILD, str(tmp_path)], stdin=subprocess.PIPE,
                         stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=env)
    try:
        port, tok = p.stdout.readline().split()
        url, origin = f"ws://127.0.0.1:{port}/ws?token={tok}", f"http://127.0.0.1:{port}"
        proc = psutil.Process(p.pid)

        async def turn(ws, steps):
            for k in range(steps):
                await ws.send(json.dumps({"type": "cmd_vel", "vx": 0, "vy": 0, "wz": 0.6, "seq": k}))
                try:
                    while True:
                        m = await asyncio.wait_for(ws.recv(), 0.05)
                        if isinstance(m, str) and json.loads(m)["type"] == "state":
                            await ws.send(json.dumps({"type": "ack", "seq": json.loads(m)["seq"]}))
                except asyncio.TimeoutError:
                    pass

        async def warm():
            async with websockets.connect(url, origin=origin) as ws:
                await turn(ws, 10)

        async def storm():
            async with websockets.connect(url, origin=origin, max_queue=4, close_timeout=0.5) as ws:
                for _ in range(5000):
                    await ws.send('{"type":"cmd_vel","vx":NaN,"vy":0,"wz":0}')
            tabs = await asyncio.gather(*[websockets.connect(url, origin=origin, max_queue=1, close_timeout=0.5)
                                         for _ in range(200)])
            await turn(tabs[0], 15)
            await asyncio.gather(*[t.close() for t in tabs])

        asyncio.run(warm())
        time.sleep(0.5)
        rss0 = proc.memory_info().rss
        asyncio.run(storm())
        time.sleep(1.0)
        grown_mb = (proc.memory_info().rss - rss0) / 2**20
        assert grown_mb < 25, f"server RSS grew {grown_mb:.1f} MB"
    finally:
        p.stdin.close()
        try:
            p.wait(30)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def test_tab_beyond_the_limit_is_told_and_closed(toy_server):
    import websockets

    server = toy_server
    server.max_clients = 2

    async def main():
        async with _connect(server) as a, _connect(server) as b:
            await asyncio.gather(_Tab(a).pump(0.5), _Tab(b).pump(0.5))
            async with _connect(server) as c:
                first = json.loads(await asyncio.wait_for(c.recv(), 5))
                assert first["type"] == "error" and "tabs are open" in first["message"]
                with pytest.raises(websockets.ConnectionClosed) as e:
                    await asyncio.wait_for(c.recv(), 5)
                assert e.value.rcvd.code == 1013
            assert len(server.clients) == 2

    asyncio.run(main())


def test_map_of_a_capture_without_floor_looks_along_its_gravity(tmp_path):
    """A capture whose gravity is +y (a camera's y-down world, as KinectFusion keeps it): the map is
    the plane perpendicular to gravity, teleport moves in that plane and keeps the height."""
    import dataclasses

    from presim.outputs.teleop.protocol import Teleport
    from presim.outputs.teleop.session import TeleopConfig, TeleopSession, _Command
    from presim.sensors.camera import CameraSpec
    from presim.sim.simulator import SimConfig, Simulator
    from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

    scene = dataclasses.replace(build_toy_room(ToyRoomConfig(width=40, height=30)), floor=None,
                                gravity_world=np.array([0.0, 1.0, 0.0]))
    sim = Simulator(scene, None, SimConfig(cameras=(CameraSpec(width=40, height=30),)))
    session = TeleopSession(sim, TeleopConfig(out_dir=tmp_path))
    R = session.R_map_world
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R @ np.array([0.0, 1.0, 0.0]), [0.0, 0.0, -1.0], atol=1e-12)   # up = map z
    caps = np.array(session.init_message(1)["captures"])
    np.testing.assert_allclose(caps[:, :2], session.to_map(np.asarray(scene.T_world_cam)[:, :3, 3])[:, :2],
                               atol=1e-3)
    sim.reset(0)
    h0 = session.to_map(sim.T_world_base[:3, 3])[2]
    u, v = (np.asarray(session.spec.map_min_xy) + np.asarray(session.spec.map_max_xy)) / 2
    session._apply(_Command(1, Teleport(float(u), float(v))))
    np.testing.assert_allclose(session.to_map(sim.T_world_base[:3, 3]), [u, v, h0], atol=1e-9)
    sim.close()


def test_cli_teleop_allow_origin_is_checked(tmp_path, capsys):
    from presim.cli import build_parser, main

    args = build_parser().parse_args(["teleop", str(tmp_path), "--allow-origin", "http://dev.example:9000",
                                      "--allow-origin", "*"])
    assert args.allow_origin == ["http://dev.example:9000", "*"] and args.tilt_deg is None and args.drive is None
    assert main(["teleop", str(tmp_path), "--allow-origin", "evil.example/page"]) == 1
    err = capsys.readouterr().err
    assert "--allow-origin 'evil.example/page'" in err and len(err.strip().splitlines()) == 1
