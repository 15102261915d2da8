"""fastcrc's CRC functions, taking any bytes-like object.

fastcrc 0.4 and later take any buffer (``bytes``, ``bytearray``, ``memoryview``); 0.3 takes
``bytes`` only, and 0.3 is what pip chooses wherever fprime-gds is installed too (its
``spacepackets`` requires ``fastcrc~=0.3.0``).  Every CRC of the project comes from here, so
decoders may hand it slices of their buffers whichever version is installed: a function that
refuses a buffer is wrapped once, at import, to copy the buffer to ``bytes`` first.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from fastcrc import crc8, crc16

Crc = Callable[..., int]


def takes_buffers(fn: Crc) -> bool:
    """Whether ``fn`` accepts a memoryview as it is."""
    try:
        fn(memoryview(b"\0"))
    except TypeError:
        return False
    return True


def any_buffer(fn: Crc) -> Crc:
    """``fn`` if it takes any buffer, else a wrapper that hands it ``bytes``."""
    if takes_buffers(fn):
        return fn

    def crc(data: Any, initial: int | None = None) -> int:
        return int(fn(data if type(data) is bytes else bytes(data), initial))

    crc.__doc__ = fn.__doc__
    return crc


#: CRC-16/MCRF4XX (X.25 without the final xor): the Aurora wire format's and MAVLink's.
mcrf4xx = any_buffer(crc16.mcrf4xx)
#: CRC-16/IBM-3740 (CCITT-FALSE): CCSDS TM and TC frames.
ibm_3740 = any_buffer(crc16.ibm_3740)
#: CRC-8/DVB-S2: CRSF.
dvb_s2 = any_buffer(crc8.dvb_s2)
#: CRC-8/SMBUS when this fastcrc has it (poly 0x07, init 0): UAVTalk.
smbus: Crc | None = any_buffer(crc8.smbus) if hasattr(crc8, "smbus") else None
