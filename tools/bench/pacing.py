"""What the benches share: messages offered at a steady rate, as a source offers them."""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from typing import TypeVar

T = TypeVar("T")


def paced_batches(items: Sequence[T], rate: float) -> Iterator[Sequence[T]]:
    """``items`` in 1 ms batches at ``rate`` per second (0: all at once); between batches
    the caller waits, as a source waits for its port."""
    if not rate:
        yield items
        return
    batch = max(1, round(rate / 1000))
    start = time.perf_counter()
    for k in range(0, len(items), batch):
        delay = start + k / rate - time.perf_counter()
        if delay > 0:
            time.sleep(delay)
        yield items[k:k + batch]
