"""Issue 44 fuzz suite (`pytest -m fuzz`): full disks, absurd sizes and geometry, concurrent writers,
malformed scene.json, recordings killed with SIGKILL, impossible depth scales.

Commands that died with a signal before (SIGBUS on a full disk) run in a subprocess, so that such a
death fails the test instead of the session. The full-disk tests mount a 2 MiB tmpfs (they run as
root in CI)."""

from __future__ import annotations

import hashlib
import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

sys.path.insert(0, str(Path(__file__).parent))
from test_capture_writers import synth_frames, write_kinfu  # noqa: E402

from presim.cli import main  # noqa: E402

pytestmark = pytest.mark.fuzz
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(autouse=True)
def _quiet(monkeypatch):
    monkeypatch.setenv("PRESIM_NO_PROGRESS", "1")
    monkeypatch.delenv("DISPLAY", raising=False)


def _env() -> dict[str, str]:
    pp = os.environ.get("PYTHONPATH", "")
    return dict(os.environ, PYTHONPATH=str(ROOT) + (os.pathsep + pp if pp else ""), PRESIM_NO_PROGRESS="1")


def _presim_sub(*args, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "presim", *map(str, args)], env=_env(), capture_output=True,
                          text=True, timeout=timeout)


def _one_error_line(err: str) -> str:
    assert "Traceback" not in err, err
    lines = [ln for ln in err.splitlines() if "error:" in ln]
    assert len(lines) == 1, err
    return lines[0]


def _call(capsys, argv: list) -> tuple[int, str]:
    """Run one command in-process: 0, 1 or 2, one error line when it fails, never a traceback."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as e:
        rc = e.code
    _, err = capsys.readouterr()
    assert "Traceback" not in err, err
    assert rc in (0, 1, 2), (rc, err)
    if rc != 0:
        _one_error_line(err)
    return rc, err


def _digest(folder: Path) -> dict[str, str]:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir())
            if p.is_file() and p.name != ".presim.lock"}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    """A 4-view 32x24 toy room, saved (no objects)."""
    from presim.capture.store import save_scene
    from presim.testing.toy_scene import ToyRoomConfig, build_toy_room

    return save_scene(build_toy_room(ToyRoomConfig(width=32, height=24, num_views=4)),
                      tmp_path_factory.mktemp("harden") / "tiny")


@pytest.fixture
def tiny_copy(tiny, tmp_path) -> Path:
    dst = tmp_path / "scene"
    shutil.copytree(tiny, dst)
    return dst


_IN_NS = "PRESIM_TEST_IN_MOUNT_NS"


@pytest.fixture
def small_tmpfs(tmp_path, request):
    """A 2 MiB tmpfs: a disk that fills. Where this process may not mount (not root), the test is
    run again inside a private user + mount namespace (``unshare -rm``), where it may; the fixture
    then gives None and the test body returns (the namespaced run has checked everything)."""
    mnt = tmp_path / "tmpfs"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(mnt)], capture_output=True, text=True)
    if r.returncode != 0:
        if os.environ.get(_IN_NS) or not shutil.which("unshare"):
            pytest.skip(f"cannot mount a tmpfs here (needs root or user namespaces: {r.stderr.strip()})")
        sub = subprocess.run(["unshare", "-rm", sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                              request.node.nodeid], cwd=ROOT, env={**_env(), _IN_NS: "1"}, capture_output=True,
                             text=True, timeout=300)
        if "cannot mount a tmpfs" in sub.stdout or sub.returncode != 0 and "unshare:" in sub.stderr:
            pytest.skip(f"cannot mount a tmpfs, not even in a user namespace: {sub.stderr.strip()[-300:]}")
        assert sub.returncode == 0 and " passed" in sub.stdout, sub.stdout[-4000:] + sub.stderr[-2000:]
        yield None
        return
    try:
        yield mnt
    finally:
        subprocess.run(["umount", "-l", str(mnt)], capture_output=True)


# ---- item 2: a full disk ------------------------------------------------------------------------

def test_full_disk_import_refine_one_line_nothing_left(small_tmpfs, tmp_path, capsys):
    if small_tmpfs is None:
        return  # checked inside a user + mount namespace (fixture small_tmpfs)
    big, small = tmp_path / "big", tmp_path / "small"
    write_kinfu(big, synth_frames(n=30, w=128, h=96, seed=1))  # 2.6 MB of arrays: more than the disk
    write_kinfu(small, synth_frames(n=6, w=128, h=96, seed=1))
    scene = small_tmpfs / "sc"

    r = _presim_sub("import", big, scene, "--no-floor")
    line = _one_error_line(r.stderr)
    assert r.returncode == 1, r.stderr
    assert "no space left on device" in line and str(scene) in line and "needs" in line
    assert list(small_tmpfs.iterdir()) == [], "a refused import left files"

    rc, _ = _call(capsys, ["import", small, scene, "--no-floor"])
    assert rc == 0
    before = _digest(scene)
    st = os.statvfs(small_tmpfs)
    free = st.f_bavail * st.f_frsize
    (small_tmpfs / "filler").write_bytes(b"\0" * (free - 64 * 1024))  # 64 KiB left; refine needs 288 KiB

    r = _presim_sub("refine", scene)
    assert r.returncode == 1, (r.returncode, r.stderr)  # not -7: a SIGBUS has no message
    line = _one_error_line(r.stderr)
    assert "no space left on device" in line and "depth_refined.npy" in line and "needs 295040 bytes" in line
    assert _digest(scene) == before
    assert not list(scene.glob("depth_refined*")), "refine left partial files"

    r = _presim_sub("import", big, scene, "--no-floor", "--overwrite")
    assert r.returncode == 1 and "no space left on device" in _one_error_line(r.stderr)
    assert _digest(scene) == before and not (small_tmpfs / "sc.partial").exists()


def test_reserved_npy_is_removed_when_the_disk_is_full(small_tmpfs):
    from presim.io_utils import DiskFullError, open_npy_for_writing

    if small_tmpfs is None:
        return  # checked inside a user + mount namespace (fixture small_tmpfs)
    with pytest.raises(DiskFullError, match=r"x\.npy: no space left on device: needs 4000128 bytes"):
        open_npy_for_writing(small_tmpfs / "x.npy", np.float32, (1000, 1000))
    assert list(small_tmpfs.iterdir()) == []
    a = open_npy_for_writing(small_tmpfs / "y.npy", np.float32, (10, 10))
    a[:] = 1
    a.flush()
    assert np.load(small_tmpfs / "y.npy").sum() == 100


# ---- item 3: absurd frame counts ----------------------------------------------------------------

def test_gen_bop_absurd_frames_refused_up_front(capsys, tiny, tmp_path):
    from presim.datasets.generate import GenConfig

    out = tmp_path / "bop"
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    rc, err = _call(capsys, ["gen-bop", tiny, "--out", out, "--frames", "1000000000000"])
    assert rc == 1 and "--frames: at most 999999" in err
    assert (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0) / 1024 < 64
    rc, err = _call(capsys, ["gen-bop", tiny, "--out", out, "--frames", "999999", "--width", "4096",
                             "--height", "4096", "--max-memory", "64G"])
    assert rc == 1 and "--frames/--width/--height" in err and "of disk" in err
    rc, err = _call(capsys, ["gen-bop", tiny, "--out", out, "--frames", "999999", "--max-memory", "1G"])
    assert rc == 1 and "--frames" in err and "frame records" in err
    assert not out.exists()
    with pytest.raises(ValueError, match="frames"):
        GenConfig(frames=10**12)


# ---- item 4: absurd geometry --------------------------------------------------------------------

@pytest.fixture
def capture(tmp_path) -> Path:
    cap = tmp_path / "cap"
    write_kinfu(cap, synth_frames(n=3, w=40, h=30, seed=1))
    return cap


def _set_pose(cap: Path, idx: int, t) -> None:
    p = sorted(cap.glob("*.pose.txt"))[idx]
    T = np.loadtxt(p)
    T[:3, 3] = t
    np.savetxt(p, T)


@pytest.mark.parametrize("case", ["far", "extent", "fx"])
def test_import_refuses_absurd_geometry(capsys, capture, tmp_path, case):
    if case == "far":
        _set_pose(capture, 1, [1e300, 0, 0])
        want = "beyond ±100 km"
    elif case == "extent":
        _set_pose(capture, 0, [-6000.0, 0, 0])
        _set_pose(capture, 2, [6000.0, 0, 0])
        want = "spread over 12.0 km"
    else:
        K = np.loadtxt(capture / "camera-intrinsics.txt")
        K[0, 0] = 1e30
        np.savetxt(capture / "camera-intrinsics.txt", K)
        want = "under 0.01 deg"
    rc, err = _call(capsys, ["import", capture, tmp_path / "sc", "--no-floor"])
    assert rc == 1 and want in err and str(capture) in err
    assert not any(tmp_path.glob("sc*"))


def test_import_8bit_depth_needs_its_unit(capsys, capture, tmp_path):
    import cv2

    for p in sorted(capture.glob("*.depth.png")):
        d = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(p), (d // 20).clip(1, 255).astype(np.uint8))
    rc, err = _call(capsys, ["import", capture, tmp_path / "sc", "--no-floor"])
    assert rc == 1 and "8-bit depth image" in err and "--depth-scale" in err
    assert not (tmp_path / "sc").exists()
    rc, _ = _call(capsys, ["import", capture, tmp_path / "sc", "--no-floor", "--depth-scale", "20"])
    assert rc == 0
    from presim.capture.store import load_scene

    d = load_scene(tmp_path / "sc").depth(0)
    assert 0.5 < float(d[d > 0].mean()) < 5.0  # metres, 20 mm per step


def test_info_never_reports_an_infinite_extent(capsys, tiny_copy):
    # float32 points at +-3e38: their float32 difference overflows to inf
    np.save(tiny_copy / "points_xyz.npy", np.array([[-3e38, 0, 0], [3e38, 1, 1]], np.float32))
    np.save(tiny_copy / "points_rgb.npy", np.zeros((2, 3), np.uint8))
    assert main(["info", str(tiny_copy)]) == 0
    ext = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("extent"))
    assert "inf" not in ext, ext
    assert main(["info", str(tiny_copy), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert all(np.isfinite(info["extent"]["size_m"])) and info["extent"]["size_m"][0] > 5e38


def test_info_refuses_a_saved_scene_with_absurd_poses(capsys, tiny_copy):
    hdr = json.loads((tiny_copy / "scene.json").read_text())
    hdr["frames"][1]["T_world_cam"][0][3] = 1e300
    (tiny_copy / "scene.json").write_text(json.dumps(hdr))
    rc, err = _call(capsys, ["info", tiny_copy])
    assert rc == 1 and "beyond ±100 km" in err and "scene.json" in err


# ---- item 5: one writer per scene ---------------------------------------------------------------

@pytest.mark.parametrize("command", ["refine", "fuse", "align", "photometric", "objects"])
def test_scene_writers_refuse_a_busy_scene_with_no_wait(capsys, tiny, command):
    from presim.io_utils import folder_lock

    with folder_lock(tiny, "presim test-holder"):
        rc, err = _call(capsys, [command, tiny, "--no-wait"])
    assert rc == 1
    line = _one_error_line(err)
    assert f"{tiny}: busy: `presim test-holder` (pid {os.getpid()}" in line and "Errno" not in line


def test_second_writer_waits_then_sees_the_first_ones_result(capsys, tiny_copy):
    from presim.io_utils import folder_lock

    lock = folder_lock(tiny_copy, "presim photometric")
    lock.__enter__()
    threading.Timer(1.0, lambda: lock.__exit__(None, None, None)).start()
    t0 = time.monotonic()
    rc, err = _call(capsys, ["photometric", tiny_copy])
    assert rc == 0 and time.monotonic() - t0 >= 0.9
    assert "waiting for `presim photometric`" in err
    rc, err = _call(capsys, ["photometric", tiny_copy])  # the first run's file is there: a clear line
    assert rc == 1 and "photometric.json: already exists" in err and "Errno" not in err


# ---- items 3/5/9a: gen-bop ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def toy_with_objects(tmp_path_factory) -> tuple[Path, Path]:
    """The 160x120 toy room with a 0.3 m box floating 1.5 m in front of its deepest view (object 1)
    and a second box outside the room that no view sees (object 2)."""
    from presim.capture.store import load_scene, save_scene
    from presim.formats.ply import write_ply
    from presim.testing.boxes import box_mesh
    from presim.testing.toy_scene import build_toy_room

    d = tmp_path_factory.mktemp("genbop")
    scene = save_scene(build_toy_room(), d / "toy")
    s = load_scene(scene)
    write_ply(d / "box.ply", *box_mesh((0.3, 0.3, 0.3)))
    i = int(np.argmax([s.depth(k)[60, 80] for k in range(len(s))]))
    T1 = np.eye(4)
    T1[:3, 3] = s.T_world_cam[i][:3, 3] + s.T_world_cam[i][:3, 2] * 1.5
    T2 = np.eye(4)
    T2[:3, 3] = [50.0, 50.0, 1.0]
    objs = [{"obj_id": 1, "model": "box.ply", "T_world_obj": T1.tolist()},
            {"obj_id": 2, "model": "box.ply", "T_world_obj": T2.tolist()}]
    (d / "one.json").write_text(json.dumps({"objects": objs[:1]}))
    (d / "two.json").write_text(json.dumps({"objects": objs}))
    return scene, d


def test_gen_bop_depth_scale_refused_and_missing_frames_never_complete(capsys, toy_with_objects, tmp_path):
    scene, d = toy_with_objects
    out = tmp_path / "bop"
    base = ["gen-bop", scene, "--out", out, "--frames", "2", "--width", "96", "--height", "72"]
    rc, err = _call(capsys, base + ["--objects", d / "one.json", "--depth-scale", "1e-9"])
    assert rc == 1 and "--depth-scale: 1e-09 mm per step stores depths up to" in err
    assert not out.exists()
    rc, err = _call(capsys, base + ["--objects", d / "two.json"])  # slot 1 targets the unseen box
    assert rc == 0, err
    rep = json.loads((out / "gen_bop_report_train_000000.json").read_text())
    assert rep["frames_written"] == 1 and rep["slots_failed"] == [1]
    assert rep["finished"] is True and rep["complete"] is False
    assert "warning: incomplete: 1 of 2 image slot(s) made no frame" in err


def test_two_gen_bop_runs_into_one_folder(capsys, toy_with_objects, tmp_path):
    from presim.io_utils import folder_lock

    scene, d = toy_with_objects
    out = tmp_path / "bop"
    args = ["gen-bop", str(scene), "--out", str(out), "--frames", "2", "--width", "96", "--height", "72",
            "--objects", str(d / "one.json")]
    sdir = out / "train" / "000000"
    sdir.mkdir(parents=True)
    with folder_lock(sdir, "presim gen-bop (other run)"):
        rc, err = _call(capsys, args + ["--no-wait"])
    assert rc == 1 and "busy: `presim gen-bop (other run)`" in err
    rcs: list[int] = []
    threads = [threading.Thread(target=lambda: rcs.append(main(args))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    err = capsys.readouterr().err
    assert rcs == [0, 0], err
    assert not (sdir / ".presim_work").exists() and (sdir / "scene_gt.json").is_file()
    assert len(list((sdir / "rgb").iterdir())) == 2


# ---- item 6: malformed scene.json ---------------------------------------------------------------

@pytest.mark.parametrize("mutate,want", [
    (lambda h: [1, 2], "top level must be a JSON object, got a JSON list"),
    (lambda h: "scene", "top level must be a JSON object, got a JSON string"),
    (lambda h: {**h, "width": "abc"}, "field 'width' must be a whole number >= 1, got 'abc'"),
    (lambda h: {**h, "height": 7}, "field 'height' says 7 but color.npy holds 24"),
    (lambda h: {**h, "frames": {"a": 1}}, "field 'frames' must be a list of objects"),
    (lambda h: {**h, "frames": h["frames"][:2]}, "field 'num_frames' is 4 but 'frames' lists 2"),
    (lambda h: {**h, "meta": [1]}, "field 'meta' must be an object"),
])
def test_info_names_the_malformed_field(capsys, tiny_copy, mutate, want):
    hdr = json.loads((tiny_copy / "scene.json").read_text())
    (tiny_copy / "scene.json").write_text(json.dumps(mutate(hdr)))
    rc, err = _call(capsys, ["info", tiny_copy])
    assert rc == 1 and want in err, err


_json = st.recursive(st.none() | st.booleans() | st.integers(-3, 10**6) | st.floats(allow_nan=False) | st.text(max_size=4),
                     lambda c: st.lists(c, max_size=3) | st.dictionaries(st.text(max_size=4), c, max_size=3),
                     max_leaves=6)


@given(key=st.sampled_from(["<top>", "format", "version", "num_frames", "width", "height", "meta", "floor", "gravity_world",
                            "objects", "frames", "has_refined_depth", "frame0", "frame0.intrinsics", "frame0.T_world_cam"]),
       value=_json)
@settings(max_examples=40, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
def test_info_on_random_scene_json_fields_never_tracebacks(capsys, tiny, tmp_path_factory, key, value):
    dst = tmp_path_factory.mktemp("sj") / "s"
    shutil.copytree(tiny, dst)
    hdr = json.loads((dst / "scene.json").read_text())
    if key == "<top>":
        hdr = value
    elif key.startswith("frame0"):
        sub = key.split(".")[1] if "." in key else None
        if sub:
            hdr["frames"][0][sub] = value
        else:
            hdr["frames"][0] = value
    else:
        hdr[key] = value
    (dst / "scene.json").write_text(json.dumps(hdr))
    _call(capsys, ["info", dst])


# ---- item 7: recordings killed with SIGKILL -----------------------------------------------------

_RECORD = """
import sys, numpy as np
from presim.capture.store import load_scene
from presim.outputs.sinks import build_sinks
from presim.sensors.camera import CameraSpec
from presim.sim.simulator import SimConfig, Simulator
out = sys.argv[2]
sim = Simulator(load_scene(sys.argv[1]), config=SimConfig(dt_s=0.1, cameras=(CameraSpec(width=32, height=24, rate_hz=10.0),)))
for s in build_sinks(__import__("pathlib").Path(out), "rrd", None):
    sim.add_sink(s)
with sim:
    sim.reset(seed=0, start=np.array([2.5, 2.0, 0.0]))
    i = 0
    while True:
        sim.step(np.array([0.0, 0.0, 0.3]))
        i += 1
        if i % 10 == 0:
            print(i, flush=True)
"""


@pytest.mark.slow
def test_recording_killed_with_sigkill_is_recovered(tiny, tmp_path):
    from mcap.reader import make_reader
    from mcap.stream_reader import StreamReader
    from rerun.chunk import RrdReader

    from presim.capture.importers import import_capture

    rec = tmp_path / "rec"
    p = subprocess.Popen([sys.executable, "-c", _RECORD, str(tiny), str(rec)], env=_env(),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # until 40 steps were made: >= 3 flushed MCAP chunks
            line = p.stdout.readline()
            if not line:
                pytest.fail(f"recorder exited early: {p.stderr.read()}")
            if int(line) >= 40:
                break
        time.sleep(0.3)
    finally:
        p.send_signal(signal.SIGKILL)
        p.wait(10)
    assert p.returncode == -signal.SIGKILL
    partial = rec / "recording.mcap.partial"
    assert partial.is_file() and not (rec / "recording.mcap").exists()
    with open(partial, "rb") as f:  # what the indexed reader could not open
        with pytest.raises(Exception):
            list(make_reader(f).iter_messages())
    readable = 0
    with open(partial, "rb") as f:
        try:
            for r in StreamReader(f).records:
                readable += type(r).__name__ == "Message"
        except Exception:  # noqa: BLE001 - the incomplete tail
            pass
    assert readable >= 30 * 6  # /clock /tf /odom /joint_states + 4 camera topics per step

    r = _presim_sub("recover", rec)
    assert r.returncode == 0, r.stderr
    assert not list(rec.glob("*.partial")), list(rec.iterdir())
    with open(rec / "recording.mcap", "rb") as f:
        reader = make_reader(f)
        n = sum(1 for _ in reader.iter_messages())
        assert n == readable == reader.get_summary().statistics.message_count
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "no footer/manifest": read by a whole-file scan
        chunks = RrdReader(rec / "recording.rrd").stream().to_chunks()
    assert sum(c.num_rows for c in chunks if c.entity_path == "/world/robot/base_link") >= 20
    cap = import_capture(rec / "capture", align_floor=False)
    assert len(cap) >= 30
    r = _presim_sub("recover", rec)
    assert r.returncode == 0 and "nothing to recover" in r.stderr
