"""The F´ JSON dictionary of the gateway's channels, so ``fprime-gds --dictionary`` decodes them.

The document follows the FPP JSON dictionary specification (``dictionarySpecVersion`` 1.0.0) as
F´ v4 writes it and fprime-gds 4.4.1 reads it: every section its loaders require is present
(empty where the gateway has nothing: no parameters, data products or packet sets), one
entry per channel of :data:`~backends.fprime.channels.CHANNELS`, the command and events of
:mod:`~backends.fprime.commands`, and the
type definitions the ground needs to decode our packets, so decoding never rests on
fprime-gds's built-in fallbacks:

- ``FwPacketDescriptorType`` (U16), ``FwChanIdType``, ``FwOpcodeType``, ``FwEventIdType``
  (U32), ``FwSizeStoreType`` (U16, the
  string channel's length prefix), ``FwTimeBaseStoreType`` (U16), ``FwTimeContextStoreType``
  (U8): aliases, as F´ v4 declares them;
- ``TimeBase`` (enum over U16, every base :data:`~backends.fprime.packets.TIME_BASES` can
  send) and ``ComCfg.Apid`` (enum over U16, F´ v4's packet descriptors): fprime-gds looks
  both up by these exact names;
- the flight-state enum :data:`~backends.fprime.channels.STATE_ENUM` (U8, the state names).

Constants: ``FW_SERIALIZE_TRUE_VALUE`` / ``FW_SERIALIZE_FALSE_VALUE`` (how a bool travels), and
``ComCfg.SpacecraftId`` / ``ComCfg.TmFrameFixedSize`` when given (fprime-gds's CCSDS deframer
reads them instead of its defaults 0x44 and 1024).
"""

from __future__ import annotations

import importlib.metadata
import json
import sys
from pathlib import Path
from typing import Any, TextIO

from backends.fprime import channels, packets
from backends.fprime.channels import CHANNELS, DEFAULT_ID_BASE, FW_TRUE, FType
from backends.fprime.commands import COMMANDS, EVENTS
from backends.fprime.framing import TM_MAX_FRAME, TM_MIN_FRAME

#: The FPP JSON dictionary specification version written.
SPEC_VERSION = "1.0.0"
#: The F´ release whose conventions (U16 descriptor, time tag, bool 0xFF, ComCfg) we follow.
FRAMEWORK_VERSION = "4.0.0"
PACKAGE = "aurora-gateway"

#: F´ v4's ``ComCfg.Apid`` constants (``config/ComCfg.fpp``): the packet descriptors.
APID_CONSTANTS: tuple[tuple[str, int, str], ...] = (
    ("FW_PACKET_COMMAND", 0x0000, "Command packet type - incoming"),
    ("FW_PACKET_TELEM", 0x0001, "Telemetry packet type - outgoing"),
    ("FW_PACKET_LOG", 0x0002, "Log type - outgoing"),
    ("FW_PACKET_FILE", 0x0003, "File type - incoming and outgoing"),
    ("FW_PACKET_PACKETIZED_TLM", 0x0004, "Packetized telemetry packet type"),
    ("FW_PACKET_DP", 0x0005, "Data product packet type"),
    ("FW_PACKET_IDLE", 0x0006, "F´ idle"),
    ("FW_PACKET_HAND", 0x00FE, "F´ handshake"),
    ("FW_PACKET_UNKNOWN", 0x00FF, "F´ unknown packet"),
    ("SPP_IDLE_PACKET", 0x07FF, "Space Packet idle APID (all ones)"),
    ("INVALID_UNINITIALIZED", 0x0800, "Not a valid APID"),
)

#: ``Fw::TimeBase``: every time base the gateway can put in a time tag.
TIME_BASE_CONSTANTS: tuple[tuple[str, int], ...] = (
    ("TB_NONE", packets.TB_NONE),
    ("TB_PROC_TIME", packets.TB_PROC_TIME),
    ("TB_WORKSTATION_TIME", packets.TB_WORKSTATION_TIME),
    ("TB_SC_TIME", packets.TB_SC_TIME),
    ("TB_FPGA_TIME", packets.TB_FPGA_TIME),
    ("TB_DONT_CARE", packets.TB_DONT_CARE),
)

_U8 = FType("U8", "integer", 8)
_U16 = FType("U16", "integer", 16)
_U32 = FType("U32", "integer", 32)
_U64 = {"name": "U64", "kind": "integer", "size": 64, "signed": False}


def _alias(name: str, underlying: FType, note: str) -> dict[str, Any]:
    d = underlying.descriptor()
    return {"kind": "alias", "qualifiedName": name, "type": d, "underlyingType": d,
            "annotation": note}


def _enum(name: str, rep: FType, constants: list[dict[str, Any]], default: str,
          note: str) -> dict[str, Any]:
    return {"kind": "enum", "qualifiedName": name, "representationType": rep.descriptor(),
            "enumeratedConstants": constants, "default": f"{name}.{default}",
            "annotation": note}


def _constant(name: str, value: int, note: str) -> dict[str, Any]:
    return {"qualifiedName": name, "type": dict(_U64), "value": value, "annotation": note}


def type_definitions() -> list[dict[str, Any]]:
    """The ``typeDefinitions`` section (independent of the id base)."""
    descriptor = packets.DESCRIPTOR.size * 8
    return [
        _alias("FwPacketDescriptorType", FType(f"U{descriptor}", "integer", descriptor),
               "The width of packet descriptors when they are serialized by the framework"),
        _alias("FwChanIdType", _U32, "The type of a telemetry channel identifier"),
        _alias("FwOpcodeType", _U32, "The type of a command opcode"),
        _alias("FwEventIdType", _U32, "The type of an event identifier"),
        _alias("FwSizeStoreType", _U16, "The type used to serialize a size value"),
        _alias("FwTimeBaseStoreType", _U16, "The type used to serialize a time base value"),
        _alias("FwTimeContextStoreType", _U8,
               "The type used to serialize a time context value"),
        _enum("TimeBase", _U16,
              [{"name": n, "value": v} for n, v in TIME_BASE_CONSTANTS], "TB_NONE",
              "Time bases of the time tags"),
        _enum("ComCfg.Apid", _U16,
              [{"name": n, "value": v, "annotation": a} for n, v, a in APID_CONSTANTS],
              "INVALID_UNINITIALIZED", "Packet descriptors (APIDs in the CCSDS framing)"),
        _enum(channels.STATE_ENUM, _U8,
              [{"name": n, "value": v} for n, v in channels.STATE_ENUM_CONSTANTS],
              channels.STATE_ENUM_CONSTANTS[0][0],
              "Flight state of the Aurora state machine SIMPLE (sm_type 0)"),
    ]


def telemetry_channels(id_base: int = DEFAULT_ID_BASE) -> list[dict[str, Any]]:
    """The ``telemetryChannels`` section: one entry per channel, id ``id_base + offset``."""
    channels.check_id_base(id_base)
    out: list[dict[str, Any]] = []
    for ch in CHANNELS:
        entry: dict[str, Any] = {"name": ch.full_name(), "type": ch.type.descriptor(),
                                 "id": id_base + ch.offset, "telemetryUpdate": "always",
                                 "annotation": ch.annotation}
        if ch.fmt:
            entry["format"] = ch.fmt
        out.append(entry)
    return out


def commands_and_events(id_base: int = DEFAULT_ID_BASE) -> tuple[list[dict[str, Any]],
                                                                  list[dict[str, Any]]]:
    """The ``commands`` and ``events`` sections (:mod:`.commands`), ids ``id_base + offset``."""
    cmds = [{"name": c.full_name(), "commandKind": "sync", "opcode": id_base + c.offset,
             "formalParams": [], "annotation": c.annotation} for c in COMMANDS]
    events = [{"name": e.full_name(), "severity": e.severity, "id": id_base + e.offset,
               "format": e.format, "annotation": e.annotation,
               "formalParams": [{"name": n, "type": {"U32": _U32}[t].descriptor(), "ref": False}
                                for n, t in e.args]} for e in EVENTS]
    return cmds, events


def project_version() -> str:
    """The installed gateway's version ("0.0.0" when it is not installed)."""
    try:
        return importlib.metadata.version(PACKAGE)
    except importlib.metadata.PackageNotFoundError:
        return "0.0.0"


def build_dictionary(id_base: int = DEFAULT_ID_BASE, *, scid: int | None = None,
                     frame_size: int | None = None) -> dict[str, Any]:
    """The whole JSON dictionary (a ``dict`` ready for :func:`json.dump`).

    ``scid`` (0..0x3FF) and ``frame_size`` (bytes of a CCSDS TM frame) add the constants
    ``ComCfg.SpacecraftId`` / ``ComCfg.TmFrameFixedSize``.  Raises ValueError on a value out
    of range.
    """
    constants = [
        _constant("FW_SERIALIZE_TRUE_VALUE", FW_TRUE, "How a serialized bool TRUE reads"),
        _constant("FW_SERIALIZE_FALSE_VALUE", 0, "How a serialized bool FALSE reads"),
    ]
    if scid is not None:
        if not 0 <= scid <= 0x3FF:
            raise ValueError(f"spacecraft id {scid} is not 0..1023 (10 bits)")
        constants.append(_constant("ComCfg.SpacecraftId", scid,
                                   "Spacecraft ID (10 bits) for CCSDS Data Link layer"))
    if frame_size is not None:
        if not TM_MIN_FRAME <= frame_size <= TM_MAX_FRAME:
            raise ValueError(f"TM frame size {frame_size} is not {TM_MIN_FRAME}..{TM_MAX_FRAME}")
        constants.append(_constant("ComCfg.TmFrameFixedSize", frame_size,
                                   "Fixed size of CCSDS TM frames"))
    cmds, events = commands_and_events(id_base)
    return {
        "metadata": {
            "deploymentName": channels.DEPLOYMENT,
            "frameworkVersion": FRAMEWORK_VERSION,
            "projectVersion": project_version(),
            "libraryVersions": [],
            "dictionarySpecVersion": SPEC_VERSION,
        },
        "typeDefinitions": type_definitions(),
        "constants": constants,
        "commands": cmds,
        "parameters": [],
        "events": events,
        "telemetryChannels": telemetry_channels(id_base),
        "records": [],
        "containers": [],
        "telemetryPacketSets": [],
    }


def write_dictionary(target: str | Path | TextIO | None = None,
                     id_base: int = DEFAULT_ID_BASE, *, scid: int | None = None,
                     frame_size: int | None = None) -> dict[str, Any]:
    """Write the dictionary as JSON to a path, an open text stream, or stdout (None, "-").

    Returns the dictionary written.  Built before the file is opened, so a bad value leaves
    no file behind.
    """
    d = build_dictionary(id_base, scid=scid, frame_size=frame_size)
    text = json.dumps(d, indent=2, ensure_ascii=False) + "\n"
    if target is None or target == "-":
        sys.stdout.write(text)
        sys.stdout.flush()
    elif isinstance(target, str | Path):
        Path(target).write_text(text, encoding="utf-8")
    else:
        target.write(text)
    return d
