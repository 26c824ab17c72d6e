"""ROS 2 set-up pieces: host-only discovery by default, the Fast DDS profile, the install line when
the ``[ros2]`` group is missing, the tf2_msgs generator's idempotence, and the ROS 1 bridge still
loading Debian's message packages when ROS 2 packages of the same names are in the venv."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from presim.outputs.ros2.env import fastdds_profile, import_rclpy, ros2_env, use_node_transport_profile

ROOT = Path(__file__).resolve().parents[1]


def test_discovery_is_host_only_unless_the_user_opens_it():
    assert ros2_env({})["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "LOCALHOST"
    assert ros2_env({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"})["ROS_AUTOMATIC_DISCOVERY_RANGE"] == "SUBNET"
    assert "ROS_AUTOMATIC_DISCOVERY_RANGE" not in ros2_env({"ROS_LOCALHOST_ONLY": "0"})


def test_fastdds_profile_receives_on_loopback_only_while_host_only(monkeypatch, tmp_path):
    assert "<address>127.0.0.1</address>" in fastdds_profile(localhost_only=True)
    assert "127.0.0.1" not in fastdds_profile(localhost_only=False)
    assert "<segment_size>16777216</segment_size>" in fastdds_profile(True)
    monkeypatch.delenv("FASTDDS_DEFAULT_PROFILES_FILE", raising=False)
    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE", raising=False)
    monkeypatch.delenv("RMW_IMPLEMENTATION", raising=False)
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    path = use_node_transport_profile()
    assert path and Path(path).read_text() == fastdds_profile(True)
    assert os.environ["FASTDDS_DEFAULT_PROFILES_FILE"] == path
    assert use_node_transport_profile() is None  # the user's (or an earlier) profile is kept


def test_missing_ros2_group_names_the_install_line(monkeypatch):
    monkeypatch.setitem(sys.modules, "rclpy", None)  # import rclpy -> ImportError
    with pytest.raises(ImportError, match=r"pip install -e '\.\[ros2\]'"):
        import_rclpy()


def test_cli_reports_the_install_line_without_ros2(tmp_path):
    code = ("import sys; sys.modules['rclpy'] = None\n"
            "from presim.cli import main\n"
            f"sys.exit(main(['ros2', {str(tmp_path)!r}]))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 1 and "presim ros2: error:" in r.stderr and "[ros2]" in r.stderr, r.stderr


def test_tf2_msgs_generator_is_idempotent():
    pytest.importorskip("rclpy", reason="needs the [ros2] group (scripts/setup.sh)")
    from presim.outputs.ros2.tf2_build import build_tf2_msgs, is_installed

    assert is_installed(), "tf2_msgs missing: run `python -m presim.outputs.ros2.tf2_build` (scripts/setup.sh)"
    t0 = time.monotonic()
    assert build_tf2_msgs() is False  # already there: nothing rebuilt
    assert time.monotonic() - t0 < 20
    from tf2_msgs.msg import TFMessage

    assert TFMessage.get_fields_and_field_types() == {"transforms": "sequence<geometry_msgs/TransformStamped>"}


def test_ros1_bridge_loads_debians_message_packages_ahead_of_ros2_ones():
    from presim.outputs.ros.env import ROS_DIST_PACKAGES

    if not os.path.isdir(os.path.join(ROS_DIST_PACKAGES, "rospy")):
        pytest.skip("needs Debian's ROS 1 packages (scripts/setup.sh --test-system)")
    code = ("from presim.outputs.ros.env import import_rospy\nimport_rospy()\n"
            "import sensor_msgs.msg, tf2_msgs.msg, rosgraph_msgs.msg\n"
            "print(sensor_msgs.__file__, tf2_msgs.__file__, rosgraph_msgs.msg.Log.__module__)")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                       env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.count(ROS_DIST_PACKAGES) == 2 and "_Log" in r.stdout


def test_ros2_command_refuses_bad_arguments_with_one_line(tmp_path, capsys):
    from presim.cli import main

    assert main(["ros2", str(tmp_path), "--rate-hz", "0"]) == 1
    assert "--rate-hz" in capsys.readouterr().err
    assert main(["ros2", str(tmp_path), "--domain-id", "300"]) == 1
    assert "--domain-id must be in 0..232" in capsys.readouterr().err
    assert main(["ros2", str(tmp_path), "--render-budget-ms", "nan"]) == 1
    assert "--render-budget-ms" in capsys.readouterr().err
    pytest.importorskip("rclpy", reason="needs the [ros2] group (scripts/setup.sh)")
    assert main(["ros2", str(tmp_path / "noscene")]) == 1
    assert "noscene" in capsys.readouterr().err


def test_ros1_and_ros2_in_one_interpreter_each_get_their_own_messages():
    """The suite runs `presim ros` and `presim ros2` in one process: each import evicts the other's
    message packages."""
    from presim.outputs.ros.env import ROS_DIST_PACKAGES, import_rospy

    if not os.path.isdir(os.path.join(ROS_DIST_PACKAGES, "rospy")):
        pytest.skip("needs Debian's ROS 1 packages (scripts/setup.sh --test-system)")
    pytest.importorskip("rclpy", reason="needs the [ros2] group (scripts/setup.sh)")
    import_rclpy()
    import sensor_msgs.msg

    assert not sensor_msgs.__file__.startswith(ROS_DIST_PACKAGES)
    import_rospy()
    import sensor_msgs.msg  # noqa: F811

    assert sensor_msgs.__file__.startswith(ROS_DIST_PACKAGES)
    import_rclpy()
    from sensor_msgs.msg import Image

    assert hasattr(type(Image), "_TYPE_SUPPORT")
