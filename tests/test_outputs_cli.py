"""`presim ros` / `presim view` argument handling (the live paths are in test_ros_bridge.py)."""

from __future__ import annotations

import pytest

from presim.cli import build_parser, main


def test_commands_registered():
    p = build_parser()
    args = p.parse_args(["ros", "scene", "--rate-hz", "5", "--robot", "free"])
    assert args.rate_hz == 5 and args.robot == "free" and args.host == "127.0.0.1"
    assert p.parse_args(["view", "x.rrd", "--web"]).web


def test_clear_errors(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("ROS_MASTER_URI", "http://127.0.0.1:9")
    monkeypatch.setenv("ROS_IP", "127.0.0.1")
    monkeypatch.setenv("ROS_HOSTNAME", "127.0.0.1")
    assert main(["view", str(tmp_path / "none.rrd")]) == 1
    assert "none.rrd" in capsys.readouterr().err
    assert main(["ros", str(tmp_path / "noscene"), "--no-roscore"]) == 1
    assert "noscene" in capsys.readouterr().err
    (tmp_path / "plain").mkdir()
    assert main(["ros", str(tmp_path / "plain"), "--no-roscore"]) == 1
    assert "not a saved scene" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["ros"])
