"""The MAVLink router's common case, compiled (``_route_speedups.c``)."""

from collections.abc import Callable
from typing import Any

def route(datagrams: list[bytes], start: int, info: dict[int, tuple[bytes, int, int, int]],
          seen: set[int], seen_at: dict[int, float], own: dict[int, Any],
          last_seq: dict[int, int], now: float,
          boxes: dict[int, tuple[dict[int, Any], ...] | None],
          boxes_of: Callable[[int], tuple[dict[int, Any], ...] | None],
          dests: dict[int, tuple[tuple[list[bytes], ...], tuple[Callable[[bytes], Any], ...]]],
          dests_of: Callable[[int], tuple[tuple[list[bytes], ...],
                                          tuple[Callable[[bytes], Any], ...]]],
          link: Any) -> tuple[int, int, int, int, int, int]: ...

def lane(rx_fd: int, recv_headers: int, batch: int, loop_fd: int, due: float,
         expect: bytes | None, route_args: tuple[Any, ...], outs: tuple[tuple[Any, ...], ...],
         in_stats: Any, framer_stats: Any, counters: Any, router: Any,
         lock: Any, batching: tuple[Any, ...], hold: float, gap: float,
         burst_min: int) -> tuple[Any, ...]: ...
