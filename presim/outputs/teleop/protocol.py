"""The teleop page's messages to the server, validated by pure functions.

Every message is one JSON object with a ``type``. :func:`parse_message` returns a typed message or
raises :class:`ProtocolError` with a one-line reason the page shows to the user; nothing a page sends
can reach the simulator without passing through it.

=============  ====================================================================================
type           fields
=============  ====================================================================================
cmd_vel        ``vx``, ``vy``, ``wz`` (m/s, m/s, rad/s, base frame), optional ``vz`` (up), ``wy`` (tilt:
               positive looks down) and ``wx`` (roll) for the free rig, optional ``seq`` (int,
               echoed in the state so the page can time key-to-motion)
joint          ``name`` (a movable joint), ``value`` (rad or m, inside the joint's limits)
teleport       ``x``, ``y`` (world metres, inside the map), optional ``yaw`` (rad)
reset          --
record         ``on`` (bool)
snapshot       --
take_control   -- (this tab becomes the one that drives)
pose           -- (the server answers ``pose``: the camera pose as a TUM line and a 4x4 matrix)
path           ``action``: ``start`` / ``stop`` (record the camera pose of every rendered frame),
               ``add`` (append the current camera pose), ``save`` (write the path as a TUM file and
               answer ``path_saved`` with its text), ``clear``
ack            ``seq`` (int: the page drew this frame; the next one may be sent)
=============  ====================================================================================
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field

__all__ = ["ProtocolError", "ProtocolSpec", "CmdVel", "JointTarget", "Teleport", "Simple", "Record", "Ack",
           "PathCommand", "PATH_ACTIONS", "parse_message", "MAX_MESSAGE_BYTES"]

MAX_MESSAGE_BYTES = 4096
PATH_ACTIONS = ("start", "stop", "add", "save", "clear")


class ProtocolError(ValueError):
    """A message the server refuses; ``str(e)`` is shown on the page."""


@dataclass(frozen=True)
class ProtocolSpec:
    """What the server accepts: the map's extent and the robot's joints."""

    map_min_xy: tuple[float, float]
    """World (x, y) of the map's lower corner, metres."""
    map_max_xy: tuple[float, float]
    """World (x, y) of the map's upper corner, metres."""
    joint_limits: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Movable joint name -> (lower, upper); +-inf for continuous joints."""
    max_speed: float = 10.0
    """|velocity| above this (m/s or rad/s) is refused as nonsense (the controller's limits apply
    below it)."""


@dataclass(frozen=True)
class CmdVel:
    vx: float
    vy: float
    wz: float
    vz: float = 0.0
    seq: int | None = None
    wy: float = 0.0
    """Pitch rate, rad/s (free rig; positive tilts the view down)."""
    wx: float = 0.0
    """Roll rate, rad/s (free rig)."""


@dataclass(frozen=True)
class JointTarget:
    name: str
    value: float


@dataclass(frozen=True)
class Teleport:
    x: float
    y: float
    yaw: float | None = None


@dataclass(frozen=True)
class PathCommand:
    """``path``: one of :data:`PATH_ACTIONS`."""

    action: str


@dataclass(frozen=True)
class Simple:
    """``reset``, ``snapshot``, ``take_control`` or ``pose``."""

    type: str


@dataclass(frozen=True)
class Record:
    on: bool


@dataclass(frozen=True)
class Ack:
    seq: int


Message = CmdVel | JointTarget | Teleport | Simple | Record | Ack | PathCommand


def _number(msg: dict, key: str, required: bool = True, default: float | None = None) -> float | None:
    if key not in msg or msg[key] is None:
        if required:
            raise ProtocolError(f"'{msg.get('type')}': missing number '{key}'")
        return default
    v = msg[key]
    # bool is an int in Python; JSON true is not a velocity.
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ProtocolError(f"'{msg.get('type')}': '{key}' must be a number, got {json.dumps(v)[:40]}")
    v = float(v)
    if not math.isfinite(v):
        raise ProtocolError(f"'{msg.get('type')}': '{key}' must be finite, got {v}")
    return v


def _int(msg: dict, key: str, required: bool) -> int | None:
    if key not in msg or msg[key] is None:
        if required:
            raise ProtocolError(f"'{msg.get('type')}': missing integer '{key}'")
        return None
    v = msg[key]
    if isinstance(v, bool) or not isinstance(v, int) or not (0 <= v < 2**53):
        raise ProtocolError(f"'{msg.get('type')}': '{key}' must be a non-negative integer")
    return v


def parse_message(raw: str | bytes, spec: ProtocolSpec) -> Message:
    """Validate one message from the page. Raises :class:`ProtocolError` (never anything else)."""
    if isinstance(raw, (bytes, bytearray)):
        if len(raw) > MAX_MESSAGE_BYTES:
            raise ProtocolError(f"message too long ({len(raw)} bytes > {MAX_MESSAGE_BYTES})")
        try:
            raw = bytes(raw).decode("utf-8")
        except UnicodeDecodeError:
            raise ProtocolError("message is not UTF-8 text") from None
    if not isinstance(raw, str):
        raise ProtocolError("message must be JSON text")
    if len(raw) > MAX_MESSAGE_BYTES:
        raise ProtocolError(f"message too long ({len(raw)} characters > {MAX_MESSAGE_BYTES})")
    try:
        msg = json.loads(raw)
    except (ValueError, RecursionError):
        raise ProtocolError("malformed message: not JSON") from None
    if not isinstance(msg, dict):
        raise ProtocolError("malformed message: expected a JSON object")
    kind = msg.get("type")
    if kind == "cmd_vel":
        v = [_number(msg, k) for k in ("vx", "vy", "wz")]
        vz, wy, wx = (_number(msg, k, required=False, default=0.0) for k in ("vz", "wy", "wx"))
        for k, x in zip(("vx", "vy", "wz", "vz", "wy", "wx"), v + [vz, wy, wx]):
            if abs(x) > spec.max_speed:
                raise ProtocolError(f"'cmd_vel': |{k}| = {abs(x):g} is above {spec.max_speed:g}")
        return CmdVel(v[0], v[1], v[2], vz, _int(msg, "seq", required=False), wy, wx)
    if kind == "joint":
        name = msg.get("name")
        if not isinstance(name, str) or name not in spec.joint_limits:
            raise ProtocolError(f"'joint': unknown joint {json.dumps(name)[:60]} "
                                f"(movable: {', '.join(spec.joint_limits) or 'none'})")
        value = _number(msg, "value")
        lo, hi = spec.joint_limits[name]
        if not lo - 1e-9 <= value <= hi + 1e-9:
            raise ProtocolError(f"'joint': {name} = {value:g} is outside its limits [{lo:g}, {hi:g}]")
        return JointTarget(name, value)
    if kind == "teleport":
        x, y = _number(msg, "x"), _number(msg, "y")
        yaw = _number(msg, "yaw", required=False)
        (x0, y0), (x1, y1) = spec.map_min_xy, spec.map_max_xy
        if not (x0 <= x <= x1 and y0 <= y <= y1):
            raise ProtocolError(f"'teleport': ({x:.2f}, {y:.2f}) is outside the map "
                                f"[{x0:.2f}, {x1:.2f}] x [{y0:.2f}, {y1:.2f}]")
        return Teleport(x, y, yaw)
    if kind in ("reset", "snapshot", "take_control", "pose"):
        return Simple(kind)
    if kind == "path":
        action = msg.get("action")
        if action not in PATH_ACTIONS:
            raise ProtocolError(f"'path': 'action' must be one of {', '.join(PATH_ACTIONS)}, "
                                f"got {json.dumps(action)[:40]}")
        return PathCommand(action)
    if kind == "record":
        on = msg.get("on")
        if not isinstance(on, bool):
            raise ProtocolError("'record': 'on' must be true or false")
        return Record(on)
    if kind == "ack":
        return Ack(_int(msg, "seq", required=True))
    raise ProtocolError(f"unknown message type {json.dumps(kind)[:40]}")
