"""The Aurora MAVLink dialect (generated module) and the per-message facts the router needs.

``mav`` is the module generated from ``dialects/aurora_mavlink.xml``: the AURORA_* messages
plus only the upstream (common + development) messages and enums the gateway encodes or
decodes, listed in ``dialects/aurora_mavlink_keep.txt``.  It is used as a value:
``mav.MAVLink(...)`` objects are created per link, never through ``mavutil`` (which rewrites
the process environment).

Every other message is routed without decoding, from the wire facts in
``dialects/mavlink_routing.py`` (generated from pymavlink's ``all.xml`` plus ours):
:data:`MESSAGES` maps every known id to its CRC_EXTRA byte (to validate frames), its largest
payload and the byte offsets of ``target_system``/``target_component`` (mavgen's rule: the
fields named exactly so) — the facts mavlink-router reads from the C library's
``mavlink_msg_entry_t`` table.  :data:`CRC_EXTRA` and :data:`TARGETS` are views of it.
"""

from __future__ import annotations

from typing import NamedTuple

from dialects import aurora_mavlink as mav
from dialects.mavlink_routing import MESSAGES as _ROWS

__all__ = ["CRC_EXTRA", "MESSAGES", "NAMES", "TARGETS", "MessageInfo", "mav"]


class MessageInfo(NamedTuple):
    """Wire facts of one message id."""

    crc_extra: int
    max_len: int  # payload length without MAVLink 2 trailing-zero truncation
    target_system_ofs: int  # byte offset in the payload, -1 when the message has none
    target_component_ofs: int


#: Every message id of pymavlink's all.xml and ours → its wire facts.
MESSAGES: dict[int, MessageInfo] = {i: MessageInfo(*row[1:]) for i, row in _ROWS.items()}
#: id → message name (for logs and counters; decoding needs ``mav``).
NAMES: dict[int, str] = {i: row[0] for i, row in _ROWS.items()}
#: id → CRC_EXTRA byte.
CRC_EXTRA: dict[int, int] = {i: m.crc_extra for i, m in MESSAGES.items()}
#: id → (target_system offset, target_component offset or -1), for targeted messages only.
TARGETS: dict[int, tuple[int, int]] = {
    i: (m.target_system_ofs, m.target_component_ofs)
    for i, m in MESSAGES.items() if m.target_system_ofs >= 0
}

#: Message ids of the Aurora messages (reserved range 45000-45099).
AURORA_ID_RANGE = range(45000, 45100)
MSG_AURORA_SM_UPDATE = mav.MAVLINK_MSG_ID_AURORA_SM_UPDATE
MSG_AURORA_STATUS = mav.MAVLINK_MSG_ID_AURORA_STATUS
