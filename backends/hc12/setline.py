"""The HC-12's SET line, pluggable: the serial port's RTS or DTR, a Linux GPIO line, or none.

SET is active low: the module is in AT-command mode while SET is held low.  "Assert" below
means "pull SET low".  Through a USB-serial adapter, an asserted RTS/DTR drives its pin low,
so SET wired to RTS is asserted with ``port.rts = True``; ``invert`` flips that for wiring
through an inverter.  pyserial asserts RTS and DTR when it opens a port, so the port must be
told to open with them deasserted (see :func:`prepare_port`).

Specs (config key ``set_line``, CLI ``--set-line``):

``none``
    SET is not wired to this host: every provisioning command refuses, pointing at the
    bench flow (the firmware's ``-ENOTSUP``);
``rts`` / ``dtr``
    the port's modem line (works through ``rfc2217://`` too);
``gpio:CHIP:LINE``
    a GPIO line through libgpiod's Python bindings (``gpiod`` ≥ 2), e.g. ``gpio:gpiochip0:17``
    or ``gpio:/dev/gpiochip0:17``; the line is requested active-low and released after use.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

from gateway.registry import extra_line

BENCH_HINT = (
    "the HC-12's SET line is not wired to this host (set_line = none): provision the module "
    "on the bench instead — pull SET low, connect a USB-serial adapter at 9600 baud and send "
    "AT commands (see backends/hc12/README.md, 'Bench provisioning'), or wire SET to the "
    "adapter's RTS/DTR or a GPIO and configure set_line")


class SetLineError(Exception):
    """The SET line cannot be driven (not wired, bindings missing, GPIO busy)."""


class SetLine(Protocol):
    """What a provisioning session needs of the SET line."""

    description: str

    def check(self) -> None:
        """Raise :class:`SetLineError` if this line cannot be used at all (before anything is
        sent)."""

    def assert_(self) -> None:
        """Pull SET low: AT-command mode."""

    def release(self) -> None:
        """Let SET go high: transparent mode.  Must not raise for a line never asserted."""


@dataclass(frozen=True)
class SetLineSpec:
    """A parsed ``set_line`` value."""

    kind: str  # "none" | "rts" | "dtr" | "gpio"
    chip: str = ""
    line: int = -1
    invert: bool = False

    def __str__(self) -> str:
        return f"gpio:{self.chip}:{self.line}" if self.kind == "gpio" else self.kind


def parse_set_line(text: str, invert: bool = False) -> SetLineSpec:
    """Parse ``none``, ``rts``, ``dtr`` or ``gpio:CHIP:LINE``; ValueError with one clear line."""
    t = text.strip()
    low = t.lower()
    if low in ("none", "rts", "dtr"):
        return SetLineSpec(low, invert=invert)
    if low.startswith("gpio:"):
        chip, sep, line = t[5:].rpartition(":")
        if sep and chip and line.isdigit():
            return SetLineSpec("gpio", chip, int(line), invert)
    raise ValueError(f"set_line: expected none, rts, dtr or gpio:CHIP:LINE "
                     f"(e.g. gpio:gpiochip0:17), got {text!r}")


class NoSetLine:
    """SET is not wired: nothing can be provisioned from here."""

    description = "none"

    def check(self) -> None:
        raise SetLineError(BENCH_HINT)

    def assert_(self) -> None:
        raise SetLineError(BENCH_HINT)

    def release(self) -> None:
        pass


class SerialSetLine:
    """SET on the port's RTS or DTR line."""

    def __init__(self, port: Any, which: str = "rts", invert: bool = False) -> None:
        if which not in ("rts", "dtr"):
            raise ValueError(f"which must be rts or dtr, not {which!r}")
        self.port = port
        self.which = which
        self.invert = invert
        self.description = which + (" (inverted)" if invert else "")

    def check(self) -> None:
        pass

    def _drive(self, active: bool) -> None:
        setattr(self.port, self.which, active != self.invert)

    def assert_(self) -> None:
        self._drive(True)

    def release(self) -> None:
        self._drive(False)


class GpioSetLine:
    """SET on a GPIO line through libgpiod (``gpiod`` ≥ 2, the kernel's v2 character device
    API).  The line is requested for the exchange and released after it, so other tools may
    use the chip meanwhile; while released the line floats — fit a pull-up on SET (the HC-12
    has an internal one)."""

    def __init__(self, chip: str, line: int, invert: bool = False) -> None:
        self.chip = chip if chip.startswith("/") else f"/dev/{chip}"
        self.line = line
        self.invert = invert
        self.description = f"gpio {self.chip} line {line}" + (" (inverted)" if invert else "")
        self._request: Any = None

    def _gpiod(self) -> Any:
        try:
            import gpiod
        except ImportError:
            raise SetLineError(extra_line("set_line gpio", "gpio")) from None
        if not hasattr(gpiod, "request_lines"):
            raise SetLineError("set_line gpio needs gpiod ≥ 2 (the installed bindings are the "
                               "1.x API): pip install -U 'gpiod>=2'")
        return gpiod

    def check(self) -> None:
        self._gpiod()

    def assert_(self) -> None:
        gpiod = self._gpiod()
        from gpiod.line import Direction, Value

        if self._request is None:
            try:
                self._request = gpiod.request_lines(
                    self.chip, consumer="aurora-gateway-hc12-set",
                    config={self.line: gpiod.LineSettings(
                        direction=Direction.OUTPUT, active_low=not self.invert,
                        output_value=Value.INACTIVE)})
            except OSError as exc:
                raise SetLineError(f"cannot request {self.description}: {exc}") from exc
        self._request.set_value(self.line, Value.ACTIVE)

    def release(self) -> None:
        req, self._request = self._request, None
        if req is None:
            return
        from gpiod.line import Value

        try:
            req.set_value(self.line, Value.INACTIVE)
        finally:
            req.release()


def make_set_line(spec: SetLineSpec, port: Any = None) -> SetLine:
    """The :class:`SetLine` for ``spec``; ``port`` is the open serial port (for rts/dtr)."""
    if spec.kind == "none":
        return NoSetLine()
    if spec.kind in ("rts", "dtr"):
        return SerialSetLine(port, spec.kind, spec.invert)
    return GpioSetLine(spec.chip, spec.line, spec.invert)


def prepare_port(port: Any, spec: SetLineSpec) -> None:
    """Set a not-yet-open port (``serial_for_url(..., do_not_open=True)``) to open with RTS and
    DTR deasserted — SET released on the configured line (inverted if so wired), and on both
    lines when ``set_line`` is none or a GPIO, in case SET is on one of them after all — so that
    opening never drops the module into AT mode."""
    port.rts = spec.invert if spec.kind == "rts" else False
    port.dtr = spec.invert if spec.kind == "dtr" else False
