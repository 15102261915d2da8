"""recvmmsg/sendmmsg's per-datagram work, compiled (``_mmsg_speedups.c``; Linux)."""

from typing import Literal, overload

@overload
def recv(fd: int, headers: int, count: int, senders: Literal[False] = ...) -> list[bytes] | int:
    ...
@overload
def recv(fd: int, headers: int, count: int, senders: Literal[True]
         ) -> tuple[list[bytes], list[bytes]] | int: ...
def send(fd: int, headers: int, count: int, datagrams: list[bytes], start: int) -> int: ...
