"""Settings of the ROS node (:class:`RosBridgeConfig`), read by the node and by its publisher sink."""

from __future__ import annotations

from dataclasses import dataclass

from presim.outputs.ros.commands import CommandLimits

__all__ = ["RosBridgeConfig"]


@dataclass(frozen=True)
class RosBridgeConfig:
    """ROS node settings."""

    node_name: str = "presim"
    """ROS node name."""
    cmd_timeout_s: float = 0.5
    """Wall seconds after the last valid /cmd_vel before the base is stopped (safety, like most drivers)."""
    real_time_factor: float = 1.0
    """Sim seconds per wall second; 0 = as fast as possible."""
    path_every_n_steps: int = 5
    """Publish /path every n steps (it grows with the drive)."""
    publisher_queue: int = 2
    """rospy publisher queue size (per subscriber; oldest dropped when a subscriber is slow)."""
    seed: int = 0
    """Seed of the start pose (and of each reset)."""
    max_steps: int = 0
    """Stop after this many steps (0 = run until Ctrl-C / rosnode kill)."""
    limits: CommandLimits = CommandLimits()
    """What commands are accepted (invalid ones are dropped)."""
    warn_period_s: float = 2.0
    """At most one /rosout warning per topic in this many wall seconds about dropped commands."""
    diagnostics_period_s: float = 1.0
    """Wall seconds between /diagnostics reports."""
