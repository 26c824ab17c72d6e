"""presim.formats: the depth-PNG rule, the strict TUM reader / writer and the capture-folder writer,
on hand-made inputs whose answers are known on paper."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from presim.formats.depth_png import depth_to_png_u16, encode_depth_png
from presim.formats.kinfu_folder import KinfuFolderWriter
from presim.formats.tum import TUM_HEADER, read_tum, tum_line, write_tum
from presim.geometry import Intrinsics, look_at


def test_depth_png_rule_and_clipped_count_mm():
    # metres -> mm, rounded; outside 1..65535 -> 0; only the far ones (+inf too) are counted.
    d = np.array([[0.0, 0.0004, 0.0006, 1.2344, 1.2346, 65.535, 65.5355, 65.536, 70.0, np.inf, np.nan, -1.0]])
    v, n = depth_to_png_u16(d, 1.0)
    assert v.dtype == np.uint16
    assert v.tolist() == [[0, 0, 1, 1234, 1235, 65535, 0, 0, 0, 0, 0, 0]]
    assert n == 4  # 65.5355 (rounds to 65536), 65.536, 70 and +inf


def test_depth_png_rule_bop_scale_and_bytes():
    # depth_scale 0.1 mm per unit: 1 m = 10000 units, the largest is 6.5535 m.
    d = np.array([[1.0, 6.5535], [6.6, 0.00004]], np.float32)
    v, n = depth_to_png_u16(d, 0.1)
    assert v.tolist() == [[10000, 65535], [0, 0]] and n == 1
    data, n2 = encode_depth_png(d, 0.1)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert n2 == 1 and back.dtype == np.uint16 and back.tolist() == v.tolist()
    with pytest.raises(ValueError, match="depth_scale_mm"):
        depth_to_png_u16(d, 0.0)


def _poses(n: int) -> np.ndarray:
    return np.stack([look_at([0.1 * k, -0.2 * k, 1.0], [1.0, 0.5 * k, 0.8]) for k in range(n)])


def test_tum_write_read_round_trip(tmp_path):
    poses, stamps = _poses(4), 100.0 + np.array([0.0, 0.1, 0.25, 1.0])
    p = tmp_path / "traj.txt"
    write_tum(p, stamps, poses)
    lines = p.read_text().splitlines()
    assert lines[0] == TUM_HEADER and len(lines) == 5 and lines[2] == tum_line(stamps[1], poses[1])
    assert lines[1].split()[:4] == ["100.000000000", f"{poses[0][0, 3]:.9f}", f"{poses[0][1, 3]:.9f}",
                                    f"{poses[0][2, 3]:.9f}"]
    s2, P2 = read_tum(p)
    np.testing.assert_allclose(s2, stamps, atol=1e-9)
    np.testing.assert_allclose(P2, poses, atol=1e-8)
    write_tum(tmp_path / "empty.txt", np.zeros(0), np.zeros((0, 4, 4)))
    assert (tmp_path / "empty.txt").read_text() == TUM_HEADER + "\n"


@pytest.mark.parametrize("text, match", [
    ("0 1 2 3\n", "bad.txt:1: a TUM line has 8 numbers"),
    ("# c\n0 1 2 3 0 0 0 one\n", "bad.txt:2: not a TUM line"),
    ("0 1 2 3 0 0 0 1\nnan 1 2 3 0 0 0 1\n", "bad.txt:2: non-finite"),
    ("0 1 2 nan 0 0 0 1\n", "bad.txt:1: non-finite"),
    ("0 1 2 3 0 0 0 0\n", "bad.txt:1: zero quaternion"),
    ("0 1 2 3 0 0 0 7\n", "bad.txt:1: quaternion norm 7"),
    ("0 1 2 3 0 0 0 1\n\n1 1 2 3 0 0 0 1\n1 1 2 3 0 0 0 1\n", "bad.txt:4: timestamps must strictly increase"),
    ("# only a comment\n", "bad.txt: empty trajectory"),
])
def test_tum_strict_reader_errors_name_file_and_line(tmp_path, text, match):
    bad = tmp_path / "bad.txt"
    bad.write_text(text)
    with pytest.raises(ValueError, match=match):
        read_tum(bad)


def test_tum_reader_accepts_comments_and_commas(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# header\n1.0, 1, 2, 3, 0, 0, 0, 1  # trailing\n2.0 0 0 0 0 0 1 0\n")
    s, P = read_tum(p)
    assert s.tolist() == [1.0, 2.0]
    np.testing.assert_allclose(P[0][:3, 3], [1, 2, 3])
    np.testing.assert_allclose(P[1][:3, :3], np.diag([-1.0, -1.0, 1.0]), atol=1e-12)  # 180 deg about z
    with pytest.raises(FileNotFoundError, match="nope.txt"):
        read_tum(tmp_path / "nope.txt")


def test_kinfu_folder_writer_round_trips_through_the_kinfu_importer(tmp_path):
    from presim.capture.importers import kinfu

    K = Intrinsics(40.0, 41.0, 15.5, 11.5, 32, 24)
    rng = np.random.default_rng(3)
    poses, stamps = _poses(3), np.array([0.5, 0.6, 0.75])
    colors = rng.integers(0, 256, (3, 24, 32, 3), dtype=np.uint8)
    depths = rng.uniform(0.5, 4.0, (3, 24, 32)).astype(np.float32)
    depths[:, 0, 0] = 0.0      # invalid stays invalid
    depths[1, 5, 5] = 80.0     # beyond 65.535 m: written 0 and counted
    w = KinfuFolderWriter(tmp_path, png_compression=1)
    for i in range(3):
        n = w.write_frame(colors[i], depths[i], poses[i], K, stamps[i], extra_images={"valid": depths[i] > 1.0})
        assert n == (1 if i == 1 else 0)
    w.close()
    assert w.frames_written == 3 and w.depth_clipped_px == 1
    with pytest.raises(ValueError, match="intrinsics changed at frame 3"):
        w.write_frame(colors[0], depths[0], poses[0], K.scaled(16, 12), 1.0)

    assert kinfu.detect(tmp_path)
    scene = kinfu.read(tmp_path)
    assert len(scene) == 3 and scene.frame_ids == ["frame-000000", "frame-000001", "frame-000002"]
    np.testing.assert_allclose(scene.intrinsics[0].K, K.K)
    np.testing.assert_allclose(scene.stamps_s, stamps, atol=1e-9)
    for i in range(3):
        np.testing.assert_allclose(scene.T_world_cam[i], poses[i], atol=1e-9)
        fr = scene.frame(i)
        np.testing.assert_array_equal(fr.color, colors[i])
        expect = np.round(depths[i].astype(np.float64) * 1000.0) / 1000.0
        expect[expect > 65.535] = 0.0
        np.testing.assert_allclose(fr.depth_m, expect, atol=1e-6)
    assert scene.frame(1).depth_m[5, 5] == 0.0 and scene.frame(0).depth_m[0, 0] == 0.0
    valid = cv2.imread(str(tmp_path / "frame-000002.valid.png"), cv2.IMREAD_UNCHANGED)
    np.testing.assert_array_equal(valid, np.where(depths[2] > 1.0, 255, 0))
    s_tum, P_tum = read_tum(tmp_path / "trajectory_tum.txt")
    np.testing.assert_allclose(s_tum, stamps)
    np.testing.assert_allclose(P_tum, poses, atol=1e-8)
