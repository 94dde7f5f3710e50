"""The decode thread of ingest: order kept, bounded look-ahead, errors in place, early stop."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
from relocdepth.ingest.prefetch import background


def test_order_and_all_items() -> None:
    assert list(background(iter(range(1000)), depth=3)) == list(range(1000))
    assert list(background(iter([]), depth=1)) == []


def test_runs_ahead_by_at_most_depth() -> None:
    produced: list[int] = []

    def source() -> Iterator[int]:
        for i in range(50):
            produced.append(i)
            yield i

    it = background(source(), depth=4)
    assert next(it) == 0
    deadline = time.monotonic() + 10.0
    while len(produced) < 6 and time.monotonic() < deadline:  # let the producer fill the queue
        time.sleep(0.01)
    time.sleep(0.2)  # and give it the chance to run further, which it must not
    # consumed 1, queued 4, and the producer holds one more it cannot put yet
    assert len(produced) == 6
    assert list(it) == list(range(1, 50))


def test_source_error_arrives_in_place() -> None:
    def source() -> Iterator[int]:
        yield 1
        yield 2
        raise ValueError("frame 3 is broken")

    it = background(source(), depth=8)
    assert next(it) == 1 and next(it) == 2
    with pytest.raises(ValueError, match="frame 3 is broken"):
        next(it)


def test_early_stop_closes_the_source() -> None:
    closed = threading.Event()

    def source() -> Iterator[int]:
        try:
            i = 0
            while True:
                yield i
                i += 1
        finally:
            closed.set()

    it = background(source(), depth=2)
    assert [next(it) for _ in range(3)] == [0, 1, 2]
    it.close()  # what a consumer's error or break does to the generator
    assert closed.wait(5.0)
    assert not any(t.name == "ingest-decode" and t.is_alive() for t in threading.enumerate())
