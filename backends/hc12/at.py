"""The HC-12 AT command set: build commands (validated), check and parse replies.

Pure: no ports, no clocks.  Facts (HC-12 user manual v2.4 and the firmware's provisioning
shell): commands are sent at 9600 baud 8N1 while SET is held low, with no line terminator;
each setting command answers one ``OK+…`` line ending in CR LF; ``AT+RX`` answers four::

    OK+FU3
    OK+B9600
    OK+C001
    OK+RP:+20dBm
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

AT_BAUD = 9600
BAUD_RATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
CHANNEL_MIN, CHANNEL_MAX = 1, 127
MODES = (1, 2, 3, 4)
#: Power level → output power in dBm (-1 dBm … +20 dBm in 3 dB steps).
POWER_DBM = {1: -1, 2: 2, 3: 5, 4: 8, 5: 11, 6: 14, 7: 17, 8: 20}
#: FU3 picks its over-the-air rate from the UART rate.
FU3_AIR_BPS = {1200: 5000, 2400: 5000, 4800: 15000, 9600: 15000, 19200: 58000, 38400: 58000,
               57600: 236000, 115200: 236000}
FACTORY = {"mode": 3, "baud": 9600, "channel": 1, "power_level": 8}
RAW_MAX_LEN = 32


class AtUsageError(ValueError):
    """An invalid argument: one line for the operator; nothing was sent."""


class AtReplyError(Exception):
    """The module answered something that is not the reply to the command."""


def channel_mhz(channel: int) -> float:
    """Centre frequency of ``channel``: 433.4 MHz plus 400 kHz a channel."""
    return round(433.4 + (channel - 1) * 0.4, 1)


@dataclass(frozen=True)
class Command:
    """One AT command and what its reply must look like.

    ``reply_lines`` None: unknown command (the raw escape hatch); the reply is whatever comes
    before the line goes quiet.  ``expect``: one full-match pattern per reply line."""

    text: str
    reply_lines: int | None = 1
    expect: tuple[str, ...] = field(default=())

    @property
    def wire(self) -> bytes:
        return self.text.encode("ascii")

    def check(self, lines: list[str]) -> None:
        """Raise :class:`AtReplyError` unless ``lines`` is the expected reply."""
        if self.reply_lines is None:
            if lines[:1] == ["ERROR"]:
                raise AtReplyError(f"the module answered ERROR to {self.text}")
            return
        if len(lines) != self.reply_lines or any(
                re.fullmatch(p, line) is None for p, line in zip(self.expect, lines, strict=False)):
            shown = " | ".join(lines) if lines else "(nothing)"
            raise AtReplyError(f"unexpected reply to {self.text}: {shown}")


def _int_arg(text: Any, what: str, lo: int, hi: int) -> int:
    try:
        value = int(str(text).strip(), 10)
    except ValueError:
        raise AtUsageError(f"{what}: expected an integer from {lo} to {hi}, got {text!r}") from None
    if not lo <= value <= hi:
        raise AtUsageError(f"{what}: expected {lo}–{hi}, got {value}")
    return value


def test() -> Command:
    return Command("AT", 1, (r"OK",))


def channel(arg: Any) -> Command:
    n = _int_arg(arg, "channel", CHANNEL_MIN, CHANNEL_MAX)
    return Command(f"AT+C{n:03d}", 1, (rf"OK\+C{n:03d}",))


def baud(arg: Any) -> Command:
    try:
        rate = int(str(arg).strip(), 10)
    except ValueError:
        rate = -1
    if rate not in BAUD_RATES:
        raise AtUsageError(f"baud: expected one of {'|'.join(map(str, BAUD_RATES))}, "
                           f"got {arg!r}")
    return Command(f"AT+B{rate}", 1, (rf"OK\+B{rate}",))


def power(arg: Any) -> Command:
    n = _int_arg(arg, "power", 1, 8)
    return Command(f"AT+P{n}", 1, (rf"OK\+P{n}",))


def mode(arg: Any) -> Command:
    n = _int_arg(arg, "mode", MODES[0], MODES[-1])
    # FU2/FU4 may also report the UART rate they forced (e.g. "OK+FU4,B1200").
    return Command(f"AT+FU{n}", 1, (rf"OK\+FU{n}(,B\d+)?",))


def info() -> Command:
    return Command("AT+RX", 4, (r"OK\+FU\d", r"OK\+B\d+", r"OK\+C\d{3}", r"OK\+RP:[+-]?\d+dBm"))


def reset() -> Command:
    return Command("AT+DEFAULT", 1, (r"OK[+_]DEFAULT",))


def raw(text: Any) -> Command:
    """The escape hatch: any printable ``AT…`` command up to 32 characters, sent as given."""
    cmd = str(text).strip()
    if not cmd.upper().startswith("AT"):
        raise AtUsageError(f"at: a command starts with AT, got {text!r}")
    if len(cmd) > RAW_MAX_LEN or not all(0x20 < ord(c) < 0x7F for c in cmd):
        raise AtUsageError(f"at: expected up to {RAW_MAX_LEN} printable ASCII characters "
                           f"without spaces, got {text!r}")
    return Command(cmd, None)


@dataclass(frozen=True)
class Settings:
    """What ``AT+RX`` reports."""

    mode: int
    baud: int
    channel: int
    power_dbm: int

    @property
    def power_level(self) -> int | None:
        for level, dbm in POWER_DBM.items():
            if dbm == self.power_dbm:
                return level
        return None

    @property
    def frequency_mhz(self) -> float:
        return channel_mhz(self.channel)

    @property
    def air_bps(self) -> int | None:
        """Over-the-air rate: FU1/FU2 250 kbps, FU3 by UART rate, FU4 500 bps."""
        return {1: 250000, 2: 250000, 4: 500}.get(self.mode, FU3_AIR_BPS.get(self.baud))

    def as_dict(self) -> dict[str, Any]:
        return {"mode": self.mode, "baud": self.baud, "channel": self.channel,
                "frequency_mhz": self.frequency_mhz, "power_level": self.power_level,
                "power_dbm": self.power_dbm, "air_bps": self.air_bps}


def parse_rx(lines: list[str]) -> Settings:
    """Turn the four lines of an ``AT+RX`` reply into :class:`Settings`."""
    info().check(lines)
    m = re.fullmatch(r"OK\+FU(\d)", lines[0])
    b = re.fullmatch(r"OK\+B(\d+)", lines[1])
    c = re.fullmatch(r"OK\+C(\d{3})", lines[2])
    p = re.fullmatch(r"OK\+RP:([+-]?\d+)dBm", lines[3])
    assert m and b and c and p  # guaranteed by check()
    return Settings(int(m[1]), int(b[1]), int(c[1]), int(p[1]))


def split_lines(data: bytes) -> tuple[list[str], bytes]:
    """Complete CR LF (or LF) terminated lines of ``data`` and the unterminated rest.

    Raises :class:`AtReplyError` on bytes an HC-12 never sends (wrong baud rate, noise)."""
    *complete, rest = re.split(rb"\r?\n", data)
    lines = []
    for raw_line in complete:
        text = raw_line.strip(b"\r")
        if any(b < 0x20 or b > 0x7E for b in text):
            raise AtReplyError(f"garbled reply {bytes(data[:48])!r}: is the host UART at "
                               f"{AT_BAUD} baud and the SET line wired?")
        if text:
            lines.append(text.decode("ascii"))
    return lines, rest
