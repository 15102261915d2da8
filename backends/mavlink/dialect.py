"""The Aurora MAVLink dialect (generated module) and the per-message facts the router needs.

``mav`` is the module generated from ``dialects/aurora_mavlink.xml`` (common + development +
the Aurora messages).  It is used as a value: ``mav.MAVLink(...)`` objects are created per
link, never through ``mavutil`` (which rewrites the process environment).

For routing without decoding, :data:`CRC_EXTRA` maps every known message id to its CRC_EXTRA
byte (to validate frames) and :data:`TARGETS` maps ids of messages that carry
``target_system``/``target_component`` to their byte offsets in the payload (mavgen's rule:
the fields named exactly so), the same facts mavlink-router reads from the C library's
``mavlink_msg_entry_t`` table.
"""

from __future__ import annotations

from typing import Any, NamedTuple

from dialects import aurora_mavlink as mav

_TYPE_SIZE = {
    "char": 1, "uint8_t": 1, "int8_t": 1, "uint16_t": 2, "int16_t": 2, "uint32_t": 4,
    "int32_t": 4, "float": 4, "uint64_t": 8, "int64_t": 8, "double": 8,
}


class MessageInfo(NamedTuple):
    """Wire facts of one message id."""

    crc_extra: int
    max_len: int  # payload length without MAVLink 2 trailing-zero truncation
    target_system_ofs: int  # byte offset in the payload, -1 when the message has none
    target_component_ofs: int


def _offsets(cls: Any) -> dict[str, int]:
    types = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
    out: dict[str, int] = {}
    ofs = 0
    for name, n in zip(cls.ordered_fieldnames, cls.array_lengths, strict=True):
        out[name] = ofs
        ofs += _TYPE_SIZE[types[name]] * max(1, n)
    return out


def _build() -> dict[int, MessageInfo]:
    table: dict[int, MessageInfo] = {}
    for msgid, cls in mav.mavlink_map.items():
        ofs = _offsets(cls)
        table[msgid] = MessageInfo(cls.crc_extra, cls.unpacker.size,
                                   ofs.get("target_system", -1),
                                   ofs.get("target_component", -1))
    return table


#: Every message id the dialect knows → its wire facts.
MESSAGES: dict[int, MessageInfo] = _build()
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
