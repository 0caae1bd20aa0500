"""``POST /views`` bodies parsed and decoded off the event loop.

JSON parsing and pydantic validation hold Python's GIL for their whole run (about 4 s for a
10⁶-point, 33 MB body on this CPU), so a worker *thread* would still stall every other request.
Bodies over :data:`IN_PROCESS_BYTES` therefore go to a small pool of worker processes, which
parse, validate and decode them into numpy arrays (:class:`~service.intake.inputs.DecodedView`);
only those arrays come back. Small bodies, the common case, are parsed in a thread: a process round
trip would cost more than the parse.

The answers match FastAPI's own body handling: a body that is not JSON is a 422 ``json_invalid``,
one that cannot be decoded a 400, a missing body a 422 ``missing``, and validation errors keep
their ``loc`` under ``body``.
"""

from __future__ import annotations

import asyncio
import email.message
import hashlib
import json
import math
import multiprocessing as mp
import re
from collections.abc import AsyncIterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import dataclass
from functools import partial

import anyio.to_thread
import numpy as np
from fastapi import HTTPException, Request, status
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError

from service.api.schemas import ViewIn
from service.intake import workers
from service.intake.inputs import DecodedView, DecodeLimits, InputError, decode_view
from service.intake.memory import ByteBudget, body_cost, decode_cost, too_many_arrays

#: Bodies up to this size are parsed in a thread of the server process.
IN_PROCESS_BYTES = 512 * 1024
#: What a body must be, said when it is not even that.
BODY_EXPECTED = (
    "the body must be one JSON object in UTF-8, sent with 'content-type: application/json' "
    "(see /docs)"
)
#: What a body nested deeper than the JSON reader's recursion limit (about 1,000 levels) hears.
TOO_DEEP = ("the body's JSON is nested too deeply (over about 1,000 levels); a view nests 3: "
            "{\"points\": [[x, y, z], …]}")


@dataclass(frozen=True)
class ParsedView:
    session_id: str | None
    view: DecodedView
    digest: str = ""  # SHA-256 of the body's bytes: an Idempotency-Key's answer is for this body


#: A 422 lists at most this many errors, then one entry counting the rest: a body of a million
#: bad points otherwise got a million errors back (331 MB for an 8.4 MB body).
MAX_ERRORS = 20


def _long_number(text: str) -> str:
    """What a body with an integer of over 4300 digits (Python's limit) gets: the key it stands
    under (the last one before it), so that the client knows which field to fix."""
    where = re.search(r"\d{4301,}", text)
    keys = re.findall(r'"([^"\\]{1,64})"\s*:', text[: where.start()]) if where else []
    field = f" ({keys[-1]})" if keys else ""
    return (f"a number in the body{field} has more than 4300 digits (the limit of this JSON "
            "reader); send ordinary numbers")


def capped(errors: list[dict]) -> list[dict]:
    """The first :data:`MAX_ERRORS` of a 422's errors and one entry counting the rest (a list
    already capped comes back as it is)."""
    if len(errors) <= MAX_ERRORS or (len(errors) == MAX_ERRORS + 1
                                     and errors[-1].get("type") == "too_many_errors"):
        return errors
    rest = len(errors) - MAX_ERRORS
    return [*errors[:MAX_ERRORS], {"loc": [], "msg": f"and {rest} more errors like these (the "
                                   f"first {MAX_ERRORS} are listed)", "type": "too_many_errors"}]


def _is_json(content_type: str | None) -> bool:
    """FastAPI's rule: no content-type, application/json or application/*+json."""
    if not content_type:
        return True
    message = email.message.Message()
    message["content-type"] = content_type
    subtype = message.get_content_subtype()
    return message.get_content_maintype() == "application" and (
        subtype == "json" or subtype.endswith("+json")
    )


def field_hint(loc: list) -> str:
    """What a field that must be a JSON object looks like (a list was sent, say)."""
    name = ".".join(str(p) for p in loc[1:])
    if loc[-1] == "intrinsics":
        return ("intrinsics is a JSON object {\"fx\": …, \"fy\": …, \"cx\": …, \"cy\": …} in "
                "pixels, not a list; from a 3×3 K: fx = K[0][0], fy = K[1][1], cx = K[0][2], "
                "cy = K[1][2]")
    return f"{name} must be a JSON object with the fields the schema gives it (see /docs)"


class _DuplicateKey(ValueError):
    """A JSON object of the body names a key twice (json.loads would keep the last)."""


def _each_key_once(pairs: list[tuple[str, object]]) -> dict:
    out: dict = {}
    for key, value in pairs:
        if key in out:
            raise _DuplicateKey(key)
        out[key] = value
    return out


def parse_view(raw: bytes, content_type: str | None, limits: DecodeLimits) -> tuple:
    """``("ok", ParsedView)`` or ``("error", status, detail)``: plain data, so that a worker
    process sends it back without pickling exceptions. ``limits``: :func:`decode_view`'s."""
    if not raw:
        return "error", 422, [{"loc": ["body"], "msg": "Field required", "type": "missing"}]
    body: object = raw
    if _is_json(content_type):
        try:
            text = raw.decode("utf-8")  # json.loads would also take UTF-16 and UTF-32 bytes
        except UnicodeDecodeError as exc:
            return "error", 400, f"the body is not UTF-8 (byte {exc.start}): {BODY_EXPECTED}"
        try:
            body = json.loads(text, object_pairs_hook=_each_key_once)
        except _DuplicateKey as exc:
            return "error", 400, (f"the key {exc.args[0]!r} appears twice in one JSON object of "
                                  "the body; give each key once")
        except json.JSONDecodeError as exc:
            return "error", 422, [{"loc": ["body", exc.pos], "msg": f"JSON decode error: "
                                   f"{exc.msg}", "type": "json_invalid"}]  # fmt: skip
        except RecursionError:
            return "error", 400, TOO_DEEP
        except ValueError:  # an integer of more than 4300 digits, the only other refusal
            return "error", 400, _long_number(text)
        del text  # its objects are what the validation reads
    try:
        view = ViewIn.model_validate(body)
    except RecursionError:
        return "error", 400, TOO_DEEP
    except ValidationError as exc:
        errors = [{"loc": ["body", *e["loc"]], "msg": e["msg"], "type": e["type"]}
                  for e in exc.errors(include_url=False, include_input=False)]  # fmt: skip
        return "error", 422, capped(errors)
    del body  # the validated copy is what is decoded: JSON's own lists go before the arrays come
    try:
        decoded = decode_view(view, limits)
    except InputError as exc:
        return "error", 422, [{"loc": list(exc.loc), "msg": exc.message, "type": "value_error"}]
    return "ok", ParsedView(view.session_id, decoded, hashlib.sha256(raw).hexdigest())


#: The warm-up body's limits: it is small and plausible whatever the settings say.
_WARM_LIMITS = DecodeLimits(1 << 20, 1 << 20, math.inf, math.inf)


def _warm_decoder() -> bool:
    """A worker's first task: parse and decode two small views (a depth PNG and float32 metres,
    with a mask), so that what decoding loads on first use (PNG codecs, validators) is loaded
    before the server answers, not during the first burst of big bodies."""
    from grasp_client.wire import b64, depth_f32_m, depth_png16_mm, png_bytes

    depth = np.full((24, 32), 0.6, dtype=np.float32)
    ok = True
    for encoded in (depth_png16_mm(depth), depth_f32_m(depth)):
        body = {"depth": encoded, "mask": b64(png_bytes(np.ones((24, 32), np.uint8))),
                "intrinsics": {"fx": 28.0, "fy": 28.0, "cx": 15.5, "cy": 11.5}}
        ok &= parse_view(json.dumps(body).encode(), "application/json", _WARM_LIMITS)[0] == "ok"
    return ok


class BodyParser:
    """Reads and parses view bodies within the memory budgets of :mod:`service.intake.memory`: small
    ones in a thread, big ones in ``workers`` processes."""

    def __init__(self, workers: int, *, limits: DecodeLimits, at_once: int, max_body_bytes: int,
                 body_memory: int, decode_memory: int, memory_wait_s: float) -> None:
        self.workers = workers
        self.limits = limits  # decode_view's: image pixels, points, plausible depth
        self.max_body_bytes = max_body_bytes
        self.bodies = ByteBudget("request bodies (GRASP_BODY_MEMORY_BYTES)", body_memory,
                                 memory_wait_s)
        self.decoding = ByteBudget("decoding views (GRASP_DECODE_MEMORY_BYTES)", decode_memory,
                                   memory_wait_s)
        self._pool: ProcessPoolExecutor | None = None
        # bodies decoded at once, threads and processes together (the CPU they take)
        self._at_once = asyncio.Semaphore(at_once)

    def _processes(self) -> ProcessPoolExecutor:
        if self._pool is None:  # started with the server (warm_up)
            self._pool = ProcessPoolExecutor(self.workers, mp_context=mp.get_context("spawn"),
                                             initializer=workers.start)
        return self._pool

    def warm_up(self) -> list:
        """Start the decoding processes now (the futures, to wait on), so that the first big
        body pays nothing and a cold server's memory is its warm one's."""
        return [self._processes().submit(_warm_decoder) for _ in range(self.workers)]

    @asynccontextmanager
    async def view(self, request: Request) -> AsyncIterator[ParsedView]:
        """The request's body read, parsed and decoded, while its bytes are reserved: the body's
        by its Content-Length before it is read, the decoding's by the pixels or JSON arrays it
        declares before it is decoded (a body with more arrays than a view's points is refused
        unparsed); both until the caller is done with the view (its answer is out)."""
        length = request.headers.get("content-length", "")
        expected = int(length) if length.isdigit() else self.max_body_bytes
        async with self.bodies.hold(body_cost(min(expected, self.max_body_bytes))):
            raw = await request.body()
            if (problem := too_many_arrays(raw, self.limits.max_points)):
                raise RequestValidationError(
                    [{"loc": ["body", "points"], "msg": problem, "type": "too_long"}])
            cost = decode_cost(raw, self.limits.max_image_pixels)
            async with self.decoding.hold(cost):
                parsed = await self.parse(raw, request.headers.get("content-type"))
                del raw
                yield parsed

    async def parse(self, raw: bytes, content_type: str | None) -> ParsedView:
        job = partial(parse_view, raw, content_type, self.limits)
        async with self._at_once:
            if len(raw) <= IN_PROCESS_BYTES:
                answer = await anyio.to_thread.run_sync(job)
            else:
                answer = await asyncio.get_running_loop().run_in_executor(self._processes(), job)
        if answer[0] == "ok":
            return answer[1]
        _, code, detail = answer
        if code == status.HTTP_422_UNPROCESSABLE_CONTENT:
            raise RequestValidationError(detail)
        raise HTTPException(code, detail)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
