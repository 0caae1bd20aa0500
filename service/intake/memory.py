"""Bounded memory for ``POST /views``: what a view body and its decoding may hold at once.

A depth view costs memory twice: its body while it is received (base64 of a 2048×2048 float32
image is 22 MB) and its decoding (the image as arrays, about :data:`DECODE_BYTES_PER_PIXEL` per
pixel at the peak, whatever the body's size: a 17 kB PNG of one constant value decodes to 4
megapixels). Two byte budgets bound them across concurrent requests:

- **bodies** (``GRASP_BODY_MEMORY_BYTES``): reserved before a body is read, by its
  Content-Length (the limit ``GRASP_MAX_BODY_BYTES`` when it has none), for the body and the
  copy sent to a decoding process;
- **decoding** (``GRASP_DECODE_MEMORY_BYTES``): reserved once the body is in, by the pixels its
  depth image declares or the JSON arrays and numbers its text holds (:func:`text_cost`),
  before anything is decoded.

A body with more JSON arrays than a view of ``GRASP_MAX_POINTS`` points can hold is refused
before it is parsed (:func:`too_many_arrays`): parsed, 32 MB of ``[0,0,1]`` (4.2 million points)
held 1.4 GB.

A request waits for room at most ``GRASP_MEMORY_WAIT_S``, then gets 503 with Retry-After; a
request bigger than a whole budget runs alone. The reservations last until the answer is out,
covering the decoded arrays the model step reads. Two budgets, not one: a request holding body
bytes may wait for decoding room, never the other way round, so they cannot wait on each other.

The bytes come back to the operating system after each request: glibc raises its mmap threshold
each time a big block is freed (up to 32 MB), after which arrays of that size live on the heap
and stay in the RSS. :func:`return_freed_memory` fixes the threshold (glibc's ``mallopt``), so a
big array is always its own mapping, given back when freed.
"""

from __future__ import annotations

import asyncio
import ctypes
import ctypes.util
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import HTTPException, status

#: Peak bytes the decoding of one depth pixel holds (base64 text, the decoded bytes, the image as
#: float32 and float64, the mask, the cleaning's buffers): measured with tracemalloc on 2048²
#: images, 24 B for float32 metres, 9 B for a 16-bit PNG.
DECODE_BYTES_PER_PIXEL = 24
#: Peak bytes a JSON array of the body holds while it is parsed and validated (the list JSON
#: makes, the one validation makes, their numbers as Python floats, the points as float64), and
#: per number beyond them. Measured with tracemalloc on 10⁵-point bodies of every shape
#: (docs/performance.md, "Memory under hostile bodies"): 256 B an array for points, realistic
#: or ``[0,0,1]`` (32 bytes per byte of text: the 6 assumed before held 1.4 GB for 32 MB), 79
#: for ``[[]]``, 67 for ``[]``; 10 B a number outside any inner array. (The text and JSON's
#: lists are let go once validated; before, 386 B an array.) 400, not 256: the budgets bound
#: RSS, and freed small objects stay in pymalloc's arenas. tests/test_memory.py checks it.
ARRAY_BYTES = 400
NUMBER_BYTES = 16
#: And per byte of text: the text as a str, its strings as objects, base64 decoded.
TEXT_BYTES = 3
#: JSON arrays a view holds besides its points' (the points' own list, camera_pose 5,
#: grid_to_camera 5, support_plane 1), plus the 128 '[' a session id could be made of.
OTHER_ARRAYS = 12 + 128
#: Copies of a body the server holds: the body read, and the copy pickled to a decoding process.
BODY_COPIES = 2

_DIMENSION = re.compile(rb'"(width|height)"\s*:\s*(\d{1,9})')

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's mallopt parameters (malloc.h)
MMAP_THRESHOLD_BYTES = 1024 * 1024


def body_cost(content_length: int) -> int:
    return BODY_COPIES * content_length


def text_cost(raw: bytes) -> int:
    """What parsing ``raw``'s JSON holds at most: :data:`ARRAY_BYTES` an array,
    :data:`NUMBER_BYTES` a number (counted by their separators), :data:`TEXT_BYTES` a byte."""
    return (ARRAY_BYTES * raw.count(b"[") + NUMBER_BYTES * (raw.count(b",") + 1)
            + TEXT_BYTES * len(raw))


def too_many_arrays(raw: bytes, max_points: int) -> str | None:
    """Why ``raw`` cannot be a view of at most ``max_points`` points, told from its count of
    '[' alone (None when it can be): each point is an array, and nothing else of a view has
    more than :data:`OTHER_ARRAYS`."""
    arrays = raw.count(b"[")
    if arrays <= max_points + OTHER_ARRAYS:
        return None
    return (f"the body holds {arrays} JSON arrays ('['); a view holds at most {max_points} "
            "points (GRASP_MAX_POINTS), one array each: send fewer points or a depth image")


def decode_cost(raw: bytes, max_pixels: int) -> int:
    """An upper bound of what decoding ``raw`` holds at its peak: the pixels its depth image
    declares (the largest ``width`` and ``height`` in the text; ``max_pixels`` when it names a
    depth image whose size cannot be read so, e.g. keys written with \\u escapes), or its
    JSON arrays and numbers (:func:`text_cost`), whichever is larger, plus the decoding
    process's copy of the body."""
    sizes = {b"width": 0, b"height": 0}
    for key, value in _DIMENSION.findall(raw):
        sizes[key] = max(sizes[key], int(value))
    pixels = sizes[b"width"] * sizes[b"height"]
    if (pixels == 0 and b'"depth"' in raw) or b"\\u" in raw:
        pixels = max_pixels
    pixels = min(pixels, max_pixels)  # a larger image is refused before it is decoded
    return max(DECODE_BYTES_PER_PIXEL * pixels, text_cost(raw)) + len(raw)


class ByteBudget:
    """Bytes held at once by requests; :meth:`hold` waits for room up to ``wait_s``, then 503."""

    def __init__(self, name: str, total: int, wait_s: float) -> None:
        self.name, self.total, self.wait_s = name, total, wait_s
        self.free = total
        self._room = asyncio.Condition()

    @asynccontextmanager
    async def hold(self, n: int) -> AsyncIterator[None]:
        n = min(n, self.total)  # bigger than the whole budget: it runs alone
        async with self._room:
            try:
                await asyncio.wait_for(self._room.wait_for(lambda: self.free >= n), self.wait_s)
            except TimeoutError:
                raise HTTPException(
                    status.HTTP_503_SERVICE_UNAVAILABLE,
                    f"the server's memory for {self.name} is taken by other requests (a budget of "
                    f"{self.total} bytes); try again shortly",
                    headers={"Retry-After": "1"},
                ) from None
            self.free -= n
        try:
            yield
        finally:
            async with self._room:
                self.free += n
                self._room.notify_all()


def return_freed_memory() -> bool:
    """Fix glibc's mmap threshold at :data:`MMAP_THRESHOLD_BYTES` (and the heap's trim threshold
    with it), so that freed arrays go back to the operating system; False where there is no
    glibc (the budgets still bound the peak)."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError, TypeError):
        return False
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES)) and bool(
        mallopt(M_TRIM_THRESHOLD, 2 * MMAP_THRESHOLD_BYTES))
