"""The ROS node: subscribers, services, the paced step loop and ``/diagnostics``.

ROS callbacks never touch the simulator: they validate a command (:mod:`.commands`), store the
latest valid one in the :class:`~presim.outputs.ros.commands.CommandInbox` under a lock
(``queue_size`` 1, rospy drops older messages) and return. Services hand a request to the loop
through a bounded list (8) and wait for its answer. So a flood of messages, valid or not, cannot
stall the loop, grow memory or end the node; invalid ones are counted, warned about on ``/rosout``
(throttled, one line per ``warn_period_s``) and reported on ``/diagnostics`` once a second.
"""

from __future__ import annotations

import threading
import time
from typing import Callable

import numpy as np

from presim.outputs.frames import MAP_FRAME
from presim.outputs.ros.commands import CommandInbox, check_pose
from presim.outputs.ros.config import RosBridgeConfig
from presim.outputs.ros.env import import_rospy
from presim.outputs.ros.messages import diagnostics_msg
from presim.outputs.ros.publisher import RosPublisherSink
from presim.sim.controllers import Action
from presim.sim.types import StepResult

__all__ = ["RosBridgeConfig", "RosBridge"]


def _pose_parts(pose):
    p, q = pose.position, pose.orientation
    return (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)


class RosBridge:
    """Runs a :class:`~presim.sim.simulator.Simulator` as a ROS node (see the module docstring)."""

    def __init__(self, sim, config: RosBridgeConfig = RosBridgeConfig(), extra_sinks: tuple = ()):
        self.sim = sim
        self.config = config
        robot = sim.robot
        joint_limits = {n: (float(lo), float(hi)) for n, lo, hi in zip(robot.joint_names, robot.lower, robot.upper)}
        self.inbox = CommandInbox(joint_limits, config.limits)
        self.publisher = self._make_publisher()
        self.extra_sinks = extra_sinks
        self.steps = 0
        self.step_errors = 0
        self._stop = threading.Event()
        self._warn_lock = threading.Lock()
        self._warned: dict[str, tuple[float, int]] = {}

    def _make_publisher(self):
        """The sink publishing every step (the ROS 2 bridge returns its own)."""
        return RosPublisherSink(self.config)

    def stop(self) -> None:
        self._stop.set()

    def _warn(self, rospy, topic: str, reason: str | None) -> None:
        """Throttled /rosout warning: at most one per topic per ``warn_period_s`` (with the number
        dropped since the previous warning)."""
        if not reason:
            return
        now = time.monotonic()
        with self._warn_lock:
            last, n = self._warned.get(topic, (-np.inf, 0))
            if now - last < self.config.warn_period_s:
                self._warned[topic] = (last, n + 1)
                return
            self._warned[topic] = (now, 0)
        more = f" (+{n} more dropped since the last warning)" if n else ""
        rospy.logwarn(f"/{topic}: dropped invalid command: {reason}{more}")

    def _init_node(self):
        rospy = import_rospy()
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped, Twist
        from nav_msgs.srv import SetMap, SetMapResponse
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Empty, EmptyResponse

        rospy.set_param("/use_sim_time", True)
        # disable_signals: Ctrl-C reaches Python as KeyboardInterrupt so our finally blocks run.
        rospy.init_node(self.config.node_name, anonymous=False, disable_signals=True)
        rospy.set_param("/robot_description", self.sim.robot.urdf_xml)
        inbox, limits = self.inbox, self.config.limits

        def on_twist(m):
            self._warn(rospy, "cmd_vel", inbox.set_twist(
                [m.linear.x, m.linear.y, m.linear.z, m.angular.x, m.angular.y, m.angular.z]))

        def on_joints(m):
            self._warn(rospy, "joint_command", inbox.set_joint_command(m.name, m.position))

        def on_reset(_req):
            inbox.request("reset", None)
            return EmptyResponse()

        def on_teleport(req):
            p = req.initial_pose
            T, reason = check_pose(*_pose_parts(p.pose.pose), p.header.frame_id, MAP_FRAME, limits)
            inbox.count("teleport", reason)
            if T is None:
                self._warn(rospy, "presim/teleport", reason)
                return SetMapResponse(success=False)
            try:
                ok = bool(inbox.request("teleport", T))
            except (ValueError, RuntimeError, TimeoutError) as e:
                self._warn(rospy, "presim/teleport", str(e))
                ok = False
            return SetMapResponse(success=ok)

        def on_initialpose(m):
            T, reason = check_pose(*_pose_parts(m.pose.pose), m.header.frame_id, MAP_FRAME, limits)
            self._warn(rospy, "initialpose", inbox.count("initialpose", reason))
            if T is not None:
                inbox.set_teleport(T)  # latest one wins; the loop applies it (no thread per message)

        self._subs = [rospy.Subscriber("/cmd_vel", Twist, on_twist, queue_size=1),
                      rospy.Subscriber("/joint_command", JointState, on_joints, queue_size=1),
                      rospy.Subscriber("/initialpose", PoseWithCovarianceStamped, on_initialpose, queue_size=1)]
        self._srvs = [rospy.Service("/presim/reset", Empty, on_reset),
                      rospy.Service("/presim/teleport", SetMap, on_teleport)]
        self._diag_pub = rospy.Publisher("/diagnostics", DiagnosticArray, queue_size=2)
        return rospy

    def _teleport(self, T: np.ndarray) -> bool:
        # A new episode starting at the pose: Action(T_world_base=...) would instead be a one-step
        # move whose huge implied velocity the acceleration limits then carry on.
        self.publisher.new_episode()
        r = self.sim.reset(self.config.seed, start=T)
        err = np.linalg.norm(r.T_world_base[:2, 3] - np.asarray(T)[:2, 3])
        return bool(err < 1e-3 and not r.contact)

    def _take_inputs(self, rospy) -> None:
        """Hook at the top of every step, before the loop reads the inbox. rospy's own threads run
        the callbacks, so nothing to do here; the ROS 2 bridge takes its inputs here."""

    def _handle_requests(self, rospy) -> None:
        T = self.inbox.take_teleport()
        if T is not None:
            try:
                self._teleport(T)
            except ValueError as e:  # e.g. a pose the scene refuses: keep the node alive
                self._warn(rospy, "initialpose", str(e))
        for kind, arg, ev, box in self.inbox.take_requests():
            try:
                if kind == "reset":
                    self.publisher.new_episode()
                    self.sim.reset(self.config.seed)
                    box.append(True)
                elif kind == "teleport":
                    box.append(self._teleport(arg))
                else:
                    box.append(ValueError(f"unknown request {kind}"))
            except Exception as e:  # answer the caller, keep the node alive
                box.append(e)
            finally:
                ev.set()

    def _step(self, rospy, action):
        """One sim step. A command the simulator still refuses (a check missing above) is logged and
        replaced by a stop, so no message can end the node."""

        try:
            return self.sim.step(action)
        except ValueError as e:
            self.step_errors += 1
            self._warn(rospy, "step", f"refused by the simulator, stopping the base: {e}")
            self.inbox.twist_wall_s = -np.inf
            return self.sim.step(Action(twist=np.zeros(6 if self.sim.is_free else 3)))

    def _publish_diagnostics(self, rospy) -> None:
        counters, last, new = self.inbox.stats()
        counters["step_errors"] = self.step_errors
        counters["steps"] = self.steps
        self._diag_pub.publish(diagnostics_msg(rospy, self.publisher.last_stamp_s, self.config.node_name,
                                               counters, last, new))

    def run(self, on_step: Callable[[StepResult], None] | None = None) -> int:
        """Spin the step loop until Ctrl-C, rospy shutdown, :meth:`stop` or ``max_steps``."""

        rospy = self._init_node()
        sim, cfg = self.sim, self.config
        sim.add_sink(self.publisher)
        for s in self.extra_sinks:
            sim.add_sink(s)
        dt = sim.config.dt_s
        try:
            sim.reset(cfg.seed)
            t0 = next_diag = time.monotonic()
            n_paced = 0
            while not self._stop.is_set() and not rospy.is_shutdown():
                if cfg.max_steps and self.steps >= cfg.max_steps:
                    break
                self._take_inputs(rospy)
                self._handle_requests(rospy)
                twist6, joints = self.inbox.current(cfg.cmd_timeout_s)
                twist = twist6 if sim.is_free else twist6[[0, 1, 5]]
                r = self._step(rospy, Action(twist=twist, joint_targets=joints or None))
                self.steps += 1
                if on_step is not None:
                    on_step(r)
                now = time.monotonic()
                if now >= next_diag:
                    self._publish_diagnostics(rospy)
                    next_diag = now + cfg.diagnostics_period_s
                if cfg.real_time_factor > 0:
                    n_paced += 1
                    lag = t0 + n_paced * dt / cfg.real_time_factor - time.monotonic()
                    if lag > 0:
                        self._stop.wait(lag)
                    elif lag < -1.0:  # far behind (slow render): re-anchor instead of bursting
                        t0, n_paced = time.monotonic(), 0
        finally:
            for kind, _, ev, box in self.inbox.take_requests():
                box.append(RuntimeError("node shutting down"))
                ev.set()
            sim.close()
            rospy.signal_shutdown("presim bridge stopped")
        return 0
