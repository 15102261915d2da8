"""The F´ backend's options, declared once (see :mod:`gateway.options`): its
``[backends.fprime]`` schema, its ``run`` flags (``--fprime``, ``--fprime-framing``) and its
documentation.  A light module (the ``aurora_gateway.backend_options`` entry point: the
standard library, :mod:`gateway.options` and the endpoint grammar); the values that the codec
modules also use are checked equal by tests/test_options.py."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from gateway.io.endpoints import STREAM_KINDS, list_validator, text_of
from gateway.options import Flag, ListenerOptions, lazy, option
from gateway.vehicles import VehicleOptions

#: The framings (``backends.fprime.framing.FRAMINGS``); the first is the default.
FRAMINGS = ("ccsds", "fprime")
DEFAULT_FRAMING = FRAMINGS[0]
#: ``backends.fprime.packets.TIME_BASES``
TIME_BASES = ("none", "proc", "workstation", "spacecraft", "fpga", "dont-care")
DEFAULT_ID_BASE = 0x100
DEFAULT_BUFFER_SIZE = 512
#: TM frame sizes: header + one 1-byte Space Packet + CRC, and the largest
TM_MIN_FRAME, TM_MAX_FRAME = 15, 2048
#: A serial endpoint's baud rate when it names none.
DEFAULT_SERIAL_BAUD = 115200
USAGE = ("tcpin:HOST:PORT (fprime-gds --ip-client connects), tcp:HOST:PORT, "
         "serial:DEVICE[,BAUD] or a pyserial URL")
#: The kinds of endpoint the backend serves (``gateway.io.links.STREAM_KINDS``).


@dataclass(frozen=True, kw_only=True)
class FprimeOptions(ListenerOptions, VehicleOptions):
    """``[backends.fprime]``: one vehicle's channels (``vehicle``; default: the first
    source's) to the F´ ground system, fprime-gds."""

    TITLE: ClassVar[str] = "F´ backend"
    endpoints: list[str] = option(
        [], USAGE, validator=list_validator(STREAM_KINDS, default_baud=DEFAULT_SERIAL_BAUD),
        flag=Flag("--fprime", "serve the rocket's channels to the F´ ground system, fprime-gds "
                  "(repeatable): tcpin:HOST:PORT (fprime-gds --ip-client connects), "
                  "tcp:HOST:PORT, serial:DEVICE[,BAUD] or a serial device / pyserial URL",
                  metavar="ENDPOINT", convert=text_of(STREAM_KINDS)))
    framing: str = option(DEFAULT_FRAMING, "ccsds (F´ v4 / fprime-gds default) or fprime",
                          choices=FRAMINGS,
                          flag=Flag("--fprime-framing", "F´ backend: ccsds (Space Packets in "
                                    "TM frames, fprime-gds's default) or fprime (DEADBEEF "
                                    "frames: fprime-gds --framing-selection fprime); default "
                                    "ccsds", metavar="FRAMING"))
    id_base: int = option(DEFAULT_ID_BASE, "id of the first channel (the dictionary's "
                          "--id-base must be the same)",
                          validator=lazy("backends.fprime.channels:check_id_base"))
    buffer_size: int = option(DEFAULT_BUFFER_SIZE, "bytes per telemetry packet "
                              "(FW_COM_BUFFER_MAX_SIZE)", minimum=32, maximum=4000)
    time_base: str = option("workstation", "time base of the time tags",
                            choices=TIME_BASES)
    time_context: int = option(0, "time context of the time tags", minimum=0, maximum=255)
    scid: int = option(0x44, "ccsds: spacecraft id (fprime-gds --scid or the dictionary's "
                       "ComCfg.SpacecraftId)", minimum=0, maximum=0x3FF)
    vcid: int = option(1, "ccsds: virtual channel id (fprime-gds --vcid)", minimum=0,
                       maximum=7)
    frame_size: int = option(1024, "ccsds: TM frame size (fprime-gds --frame-size or the "
                             "dictionary's ComCfg.TmFrameFixedSize)", minimum=TM_MIN_FRAME,
                             maximum=TM_MAX_FRAME)
    queue_depth: int = option(64, "writes waiting per peer before drops", minimum=1,
                              maximum=4096)
