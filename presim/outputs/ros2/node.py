"""The ROS 2 node: subscribers, services and ``/diagnostics`` on rclpy; the rest is the ROS 1 bridge's.

:class:`Ros2Bridge` is a :class:`~presim.outputs.ros.node.RosBridge` whose transport is rclpy: the
paced step loop, the command validation (:mod:`presim.outputs.ros.commands`, the same rules and
counters), the request hand-over to the loop, the step-error fallback and the throttled warnings are
shared code, so the two bridges accept and drop exactly the same commands.

Inputs are taken by the step loop, not by the executor: at the top of every step the loop takes
the messages waiting on ``/cmd_vel``, ``/joint_command`` and ``/initialpose`` (the middleware keeps
the newest ``command`` QoS depth, 10, of each) and runs the validating callbacks on them. Their
callback group (``_polled_group``) tells the executor never to run them. So the Python work for
inputs is at most ``MAX_TAKEN_PER_STEP`` messages per topic per step whatever the senders' rate, and a flood costs the
node only the middleware's own (C++, GIL-free) receive work. Run by rclpy's Python executor instead,
a 1 kHz ``/cmd_vel`` flood kept the executor thread holding the GIL and the step loop, which gives up
the GIL at every numba kernel and publish, waiting for it: 0.4-5 steps/s of 10 (docs/ros2.md).

Threads: an rclpy ``SingleThreadedExecutor`` runs the services (and the node's own ``/clock`` and
parameter callbacks) in a daemon thread; the services hand a request to the loop through the bounded
inbox and wait for the answer. Not the ``MultiThreadedExecutor``: rclpy's re-queues a task that its pool
has not started yet and returns from its wait at once while one is queued (rclpy issue 1452, fixed
upstream by PR 1547, not in the installed release), so its spin thread held the GIL at 100 % of a core
for 0.3-1 s at a time, and the step loop, waiting for the GIL, published 5.7-9 frames/s instead of 10.
The step loop runs in the caller's thread, takes the inputs and publishes. rclpy's own signal handlers are off: Ctrl-C
and SIGTERM reach Python (``presim.cli.main`` turns SIGTERM into KeyboardInterrupt), so the loop's
``finally`` closes every sink and the node.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from presim.outputs.frames import MAP_FRAME
from presim.outputs.ros.commands import check_pose
from presim.outputs.ros.node import RosBridge, RosBridgeConfig
from presim.outputs.ros2.env import import_rclpy, use_node_transport_profile
from presim.outputs.ros2.messages import diagnostics_msg, qos_profiles
from presim.outputs.ros2.publisher import Ros2PublisherSink

__all__ = ["Ros2BridgeConfig", "Ros2Bridge", "take_waiting"]

MAX_TAKEN_PER_STEP = 20
"""Messages taken per input topic per step at most: the ``command`` QoS depth (10), plus those
arriving while the loop takes them; a bound, so that a flood cannot hold the loop."""


@dataclass(frozen=True)
class Ros2BridgeConfig(RosBridgeConfig):
    """ROS 2 node settings (the ROS 1 bridge's, plus these)."""

    reliable_camera_topics: bool = True
    """Also offer the camera topics reliably under ``/<camera>/reliable/...`` (RViz2's default QoS)."""
    use_sim_time: bool = True
    """The node's own ``use_sim_time`` parameter (its clock follows the ``/clock`` it publishes)."""
    domain_id: int | None = None
    """ROS_DOMAIN_ID of the node; None = the environment's (default 0)."""


def _polled_group():
    """A callback group that no executor runs: the step loop takes its subscriptions' messages
    (:func:`take_waiting`) and calls their callbacks itself. (Defined here, not at import: rclpy is
    optional.)"""
    from rclpy.callback_groups import CallbackGroup

    class PolledGroup(CallbackGroup):
        def can_execute(self, entity) -> bool:
            return False  # the executor then leaves the entity out of its wait set

        def beginning_execution(self, entity) -> bool:
            return False

    return PolledGroup()


def take_waiting(sub, limit: int = MAX_TAKEN_PER_STEP) -> int:
    """Take up to ``limit`` messages waiting on rclpy subscription ``sub`` (oldest first) and call
    ``sub.callback(msg, received_s)`` on each, ``received_s`` being its arrival time on the
    ``time.monotonic()`` clock. Returns the number taken."""
    from rclpy.exceptions import InvalidHandle

    n = 0
    try:
        with sub.handle:
            while n < limit:
                got = sub.handle.take_message(sub.msg_type, sub.raw)
                if got is None:
                    break
                msg, info = got
                # received_timestamp: the middleware's arrival time (system clock, ns; 0 = unknown)
                age_s = (time.time_ns() - int(info.get("received_timestamp", 0))) * 1e-9
                now_s = time.monotonic()
                sub.callback(msg, now_s - age_s if 0.0 <= age_s < 60.0 else now_s)
                n += 1
    except InvalidHandle:  # destroyed under us: the node is shutting down
        pass
    return n


def _pose_parts(pose):
    p, q = pose.position, pose.orientation
    return (p.x, p.y, p.z), (q.x, q.y, q.z, q.w)


class _Transport:
    """The calls :class:`RosBridge`'s loop makes on ``rospy`` (``logwarn``, ``is_shutdown``,
    ``signal_shutdown``), answered by an rclpy node, its context and executor."""

    def __init__(self, rclpy, context, node, executor, thread):
        self.rclpy, self.context, self.node, self.executor, self.thread = rclpy, context, node, executor, thread

    def logwarn(self, msg: str) -> None:
        self.node.get_logger().warning(msg)

    def is_shutdown(self) -> bool:
        return not self.context.ok()

    def signal_shutdown(self, reason: str) -> None:
        # Order matters: stop the executor and its thread, then destroy the node (and with it every
        # publisher, subscription and service), then the context.
        try:
            self.executor.shutdown(timeout_sec=10.0)
            self.thread.join(timeout=10.0)
        finally:
            try:
                self.node.destroy_node()
            finally:
                self.rclpy.try_shutdown(context=self.context)


class Ros2Bridge(RosBridge):
    """Runs a :class:`~presim.sim.simulator.Simulator` as a ROS 2 node (see the module docstring)."""

    def __init__(self, sim, config: Ros2BridgeConfig = Ros2BridgeConfig(), extra_sinks: tuple = ()):
        super().__init__(sim, config, extra_sinks)

    def _make_publisher(self):
        return Ros2PublisherSink(self.config)

    def _init_node(self):
        rclpy = import_rclpy()
        use_node_transport_profile()
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseWithCovarianceStamped, Twist
        from nav_msgs.srv import SetMap
        from rclpy.callback_groups import MutuallyExclusiveCallbackGroup
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.parameter import Parameter
        from rclpy.signals import SignalHandlerOptions
        from sensor_msgs.msg import JointState
        from std_srvs.srv import Empty

        cfg = self.config
        context = rclpy.context.Context()
        rclpy.init(context=context, domain_id=cfg.domain_id, signal_handler_options=SignalHandlerOptions.NO)
        node = rclpy.create_node(cfg.node_name, context=context, parameter_overrides=[
            Parameter("use_sim_time", Parameter.Type.BOOL, cfg.use_sim_time)])
        self.publisher.node = node
        inbox, limits, qos = self.inbox, cfg.limits, qos_profiles()
        polled, srv_group = _polled_group(), MutuallyExclusiveCallbackGroup()
        transport = None  # set below; the callbacks only run once the loop / the executor runs

        def on_twist(m, received_s=None):
            self._warn(transport, "cmd_vel", inbox.set_twist(
                [m.linear.x, m.linear.y, m.linear.z, m.angular.x, m.angular.y, m.angular.z], received_s))

        def on_joints(m, _received_s=None):
            self._warn(transport, "joint_command", inbox.set_joint_command(m.name, m.position))

        def on_initialpose(m, _received_s=None):
            T, reason = check_pose(*_pose_parts(m.pose.pose), m.header.frame_id, MAP_FRAME, limits)
            self._warn(transport, "initialpose", inbox.count("initialpose", reason))
            if T is not None:
                inbox.set_teleport(T)  # latest one wins; the loop applies it

        def on_reset(_req, resp):
            try:
                inbox.request("reset", None)
            except (RuntimeError, TimeoutError) as e:
                self._warn(transport, "presim/reset", str(e))
            return resp

        def on_teleport(req, resp):
            p = req.initial_pose
            T, reason = check_pose(*_pose_parts(p.pose.pose), p.header.frame_id, MAP_FRAME, limits)
            inbox.count("teleport", reason)
            resp.success = False
            if T is None:
                self._warn(transport, "presim/teleport", reason)
                return resp
            try:
                resp.success = bool(inbox.request("teleport", T))
            except (ValueError, RuntimeError, TimeoutError) as e:
                self._warn(transport, "presim/teleport", str(e))
            return resp

        c = qos["command"]
        self._subs = [node.create_subscription(Twist, "/cmd_vel", on_twist, c, callback_group=polled),
                      node.create_subscription(JointState, "/joint_command", on_joints, c, callback_group=polled),
                      node.create_subscription(PoseWithCovarianceStamped, "/initialpose", on_initialpose, c,
                                               callback_group=polled)]

        self._srvs = [node.create_service(Empty, "/presim/reset", on_reset, callback_group=srv_group),
                      node.create_service(SetMap, "/presim/teleport", on_teleport, callback_group=srv_group)]
        self._diag_pub = node.create_publisher(DiagnosticArray, "/diagnostics", qos["default"])
        executor = SingleThreadedExecutor(context=context)
        executor.add_node(node)
        thread = threading.Thread(target=self._spin, args=(executor,), name="presim-ros2-executor", daemon=True)
        transport = _Transport(rclpy, context, node, executor, thread)
        thread.start()
        return transport

    def _take_inputs(self, transport) -> None:
        for sub in self._subs:
            take_waiting(sub)

    @staticmethod
    def _spin(executor) -> None:
        try:
            executor.spin()
        except Exception:  # the context was shut down under it: the loop ends through is_shutdown()
            pass

    def _publish_diagnostics(self, transport) -> None:
        counters, last, new = self.inbox.stats()
        counters["step_errors"] = self.step_errors
        counters["steps"] = self.steps
        counters["uptime_ms"] = int(time.monotonic() * 1e3)  # the node's clock: rates that ignore delivery lag
        self._diag_pub.publish(diagnostics_msg(self.publisher.last_stamp_s, self.config.node_name, counters,
                                               last, new))
