"""Attitude arithmetic shared by the backends that carry it as a quaternion (UAVTalk's
AttitudeState, Foxglove's FrameTransform, the MCAP export)."""

from __future__ import annotations

import math


def quaternion_wxyz(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """(w, x, y, z) of the rotation yaw about z, then pitch about the new y, then roll about
    the newest x (the aerospace Z-Y-X convention: body → world), angles in radians."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy)


def quaternion_xyzw(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """The same rotation as :func:`quaternion_wxyz`, scalar last (ROS, Foxglove)."""
    w, x, y, z = quaternion_wxyz(roll, pitch, yaw)
    return x, y, z, w
