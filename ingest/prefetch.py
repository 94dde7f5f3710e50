"""Running a source's frame iterator in its own thread, so decoding overlaps encoding and writing.

A video's frames are decoded by ``cv2.VideoCapture`` (which releases the GIL), then encoded in a
worker pool and written in the main thread. With the decoder on the main thread, every write and
every wait for the oldest encoded frame stalls decoding; in its own thread it runs ahead, by at
most ``depth`` frames (bounded memory), and order is kept by the queue.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Iterator
from typing import TypeVar

T = TypeVar("T")

_DONE = object()
# How often a blocked producer checks whether the consumer went away (seconds).
POLL_S = 0.1


class _Failed:
    def __init__(self, error: BaseException) -> None:
        self.error = error


def background(items: Iterator[T], depth: int) -> Iterator[T]:
    """Yield ``items`` in order while a thread produces up to ``depth`` of them ahead.

    An exception raised by ``items`` is re-raised here, at its place in the order. When the
    consumer stops early (an error, ``break``), the producer stops at its next item and the
    source iterator is closed in the producer's thread.
    """
    if depth < 1:
        raise ValueError(f"depth must be >= 1, got {depth}")
    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()

    def put(obj: object) -> bool:
        while not stop.is_set():
            try:
                q.put(obj, timeout=POLL_S)
                return True
            except queue.Full:
                continue
        return False

    def produce() -> None:
        try:
            for item in items:
                if not put(item):
                    return
            put(_DONE)
        except BaseException as e:  # noqa: BLE001 (handed to the consumer)
            put(_Failed(e))
        finally:
            close = getattr(items, "close", None)
            if close is not None:
                close()

    worker = threading.Thread(target=produce, name="ingest-decode", daemon=True)
    worker.start()
    try:
        while True:
            obj = q.get()
            if obj is _DONE:
                return
            if isinstance(obj, _Failed):
                raise obj.error
            yield obj
    finally:
        stop.set()
        worker.join()
