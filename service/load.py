"""``python -m service.load``: a bounded load test of a running service on this machine.

Streams the 12 views of simulated camera_pan scenes into ``--sessions`` sessions
(``--concurrency`` of them at a time), then asks each for a grasp (``--grasp-every-view``:
after every view that shows the object, as a robot would), and prints the latency
percentiles per route, the errors, and lost views (views answered 200 but missing from the
session afterwards). Talks to loopback addresses only, and stops by itself::

    python -m service &                       # or any running server
    python -m service.load --url http://127.0.0.1:8000 --sessions 32 --views 12
    python -m service.load --url http://127.0.0.1:8000 --sessions 2 --grasp-every-view
    python -m service.load --url http://127.0.0.1:8000 --condition clutter --sessions 2 --views 4

With ``--neighbour-token`` another client (a second token of ``GRASP_TOKEN``) keeps
``--neighbour-requests`` verified ``GET /grasp`` going on a session of its own for the whole run:
the measured client's latencies then say how much a heavy neighbour costs it (fair planners)::

    GRASP_TOKEN=tokA,tokB python -m service &
    python -m service.load --token tokB --condition tabletop --sessions 4 --views 4 \
        --grasp-every-view --verify 0 --neighbour-token tokA
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ipaddress
import itertools
import json
import os
import sys
import time
from collections import defaultdict
from dataclasses import dataclass, field
from urllib.parse import urlparse

import numpy as np

from completion.cli import HelpWithDefaults

ROUTES = ("POST /views", "GET /grasp", "GET /sessions/{id}", "DELETE /sessions/{id}")
#: The neighbour's routes (``--neighbour-token``): reported, never a failure of the run.
NEIGHBOUR = "GET /grasp (neighbour)"


@dataclass
class Tally:
    latency_ms: dict[str, list[float]] = field(default_factory=lambda: defaultdict(list))
    errors: dict[str, list[str]] = field(default_factory=lambda: defaultdict(list))
    grasp_timing_ms: list[dict[str, float]] = field(default_factory=list)
    views_sent: int = 0
    views_lost: int = 0
    bad_indices: int = 0

    def summary(self) -> dict:
        routes = {}
        for route in (*ROUTES, NEIGHBOUR):
            lat = np.asarray(self.latency_ms.get(route, []), dtype=float)
            if not len(lat) and not self.errors.get(route):
                continue
            routes[route] = {
                "requests": int(len(lat)),
                "p50_ms": _pct(lat, 50),
                "p99_ms": _pct(lat, 99),
                "max_ms": float(lat.max()) if len(lat) else None,
                "errors": len(self.errors.get(route, [])),
            }
        split = {}
        for key in ("load", "completion", "mesh", "planning", "waiting", "total"):
            values = [t[key] for t in self.grasp_timing_ms if key in t]
            if values:
                split[key] = {
                    "p50_ms": _pct(np.asarray(values), 50),
                    "p99_ms": _pct(np.asarray(values), 99),
                }
        return {
            "routes": routes,
            "grasp_timing_ms": split,
            "views_sent": self.views_sent,
            "views_lost": self.views_lost,
            "out_of_order_view_indices": self.bad_indices,
            "error_samples": {r: e[:3] for r, e in self.errors.items() if e},
        }


def _pct(values: np.ndarray, q: float) -> float | None:
    return round(float(np.percentile(values, q)), 1) if len(values) else None


def check_loopback(url: str) -> str:
    """The URL without a trailing slash; ValueError unless it is http(s) on a loopback host."""
    parsed = urlparse(url)
    if parsed.scheme not in ("http", "https") or not parsed.hostname:
        raise ValueError(f"--url must look like http://127.0.0.1:8000, got {url!r}")
    host = parsed.hostname
    if host != "localhost":
        try:
            loopback = ipaddress.ip_address(host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(f"the load generator only talks to loopback hosts, got {host!r}")
    return url.rstrip("/")


def scene_views(sequence, *, with_pose: bool = True) -> list[dict]:
    """``POST /views`` bodies (without session_id) for a simulated sequence kept with depth.

    ``sequence``: a :class:`completion.scenes.Sequence` made with ``keep_depth=True``; each view is
    a 16-bit millimetre depth PNG with its object mask and intrinsics, and (with_pose) its camera
    pose, encoded as the client encodes them (:mod:`grasp_client.wire`).
    """
    from grasp_client.wire import depth_png16_mm, intrinsics_field, mask_png

    if sequence.depth is None or sequence.mask is None:
        raise ValueError("the sequence has no depth images: make it with keep_depth=True")
    intrinsics = intrinsics_field(sequence.meta["intrinsics"])
    bodies = []
    for t in range(len(sequence.depth)):
        body = {
            "depth": depth_png16_mm(sequence.depth[t]),
            "intrinsics": intrinsics,
            "mask": mask_png(sequence.mask[t] >= 0),
        }
        if with_pose:
            body["camera_pose"] = sequence.camera_to_world[t].tolist()
        bodies.append(body)
    return bodies


def make_bodies(
    n_scenes: int, views: int, seed: int, condition: str = "camera_pan"
) -> list[list[dict]]:
    """``n_scenes`` simulated scenes of ``condition`` (test split) as lists of view bodies; a
    tabletop scene's first view carries its table as the session's support plane; a clutter
    scene (:func:`clutter_views`) is the clutter table's."""
    from completion.scenes import make_sequence

    if condition == "clutter":
        return [clutter_views(i, seed, views) for i in range(n_scenes)]
    scenes = []
    for i in range(n_scenes):
        seq = make_sequence(condition, "test", i, seed, views=views, keep_depth=True)
        bodies = scene_views(seq)
        if "support_plane" in seq.meta:
            bodies[0]["support_plane"] = list(seq.meta["support_plane"])
        scenes.append(bodies)
    return scenes


def clutter_views(index: int, seed: int, views: int) -> list[dict]:
    """The clutter table's scene ``index`` (:func:`grasp.evaluate.clutter_scenes.
    make_clutter_scene`: a target among 2-5 neighbours on a table) as view bodies: each a depth
    PNG with its label image (the target 1, the neighbours 2, the rest 0), its camera pose, the
    table with the first. The scene has 4 views; more are its pan again."""
    from completion.scenes import TABLE_PLANE
    from grasp.evaluate.clutter_scenes import make_clutter_scene
    from grasp_client.wire import depth_png16_mm, intrinsics_field

    scene = make_clutter_scene(index, seed)
    k = scene.intrinsics
    bodies = []
    for i in range(views):
        t = i % len(scene.depth)
        bodies.append({"depth": depth_png16_mm(scene.depth[t]),
                       "intrinsics": intrinsics_field({"fx": k.fx, "fy": k.fy, "cx": k.cx,
                                                       "cy": k.cy}),
                       "mask": _label_png(scene.labels(t)),
                       "object_label": scene.TARGET, "camera_pose": scene.cameras[t].tolist()})
    bodies[0]["support_plane"] = TABLE_PLANE.as_array().tolist()
    return bodies


def _label_png(labels: np.ndarray) -> str:
    """A label image as the ``mask`` field (8-bit PNG, the values as they are)."""
    from grasp_client.wire import b64, png_bytes

    return b64(png_bytes(labels))


async def _timed(client, tally: Tally, route: str, method: str, url: str, **kwargs):
    start = time.perf_counter()
    try:
        response = await client.request(method, url, **kwargs)
    except Exception as exc:  # a load test counts transport failures instead of stopping
        tally.errors[route].append(f"{type(exc).__name__}: {exc}")
        return None
    tally.latency_ms[route].append((time.perf_counter() - start) * 1e3)
    if response.status_code >= 400:
        tally.errors[route].append(f"{response.status_code}: {response.text[:200]}")
        return None
    return response


async def _grasp(client, tally: Tally, session_id: str, args) -> None:
    params = {"session_id": session_id, "top_k": 1, "n_candidates": args.n_candidates}
    if args.verify is not None:
        params["verify"] = args.verify
    r = await _timed(client, tally, "GET /grasp", "GET", "/grasp", params=params)
    if r is not None:
        tally.grasp_timing_ms.append(r.json()["timing_ms"])


async def _session(client, tally: Tally, bodies: list[dict], args) -> None:
    session_id, indices = None, []
    for body in bodies:
        payload = body if session_id is None else {**body, "session_id": session_id}
        tally.views_sent += 1
        r = await _timed(client, tally, "POST /views", "POST", "/views", json=payload)
        if r is None:
            if session_id is None:
                return
            continue
        session_id = r.json()["session_id"]
        indices.append(r.json()["view_index"])
        if args.grasp_every_view and r.json()["occupied_voxels"] > 0:  # seen: 409 before
            await _grasp(client, tally, session_id, args)
    if indices != list(range(len(indices))):
        tally.bad_indices += 1
    if not args.grasp_every_view:
        await _grasp(client, tally, session_id, args)
    r = await _timed(client, tally, "GET /sessions/{id}", "GET", f"/sessions/{session_id}")
    if r is not None:
        tally.views_lost += len(indices) - r.json()["views"]
    if not args.keep:
        await _timed(client, tally, "DELETE /sessions/{id}", "DELETE", f"/sessions/{session_id}")


async def _neighbour(args, views: list[dict], tally: Tally, started: asyncio.Event) -> None:
    """Another client: one session of ``views``, then ``--neighbour-requests`` verified
    ``GET /grasp`` at a time until cancelled, each a plan no cache holds (n_candidates cycles)."""
    import httpx

    headers = {"Authorization": f"Bearer {args.neighbour_token}"}
    limits = httpx.Limits(max_connections=args.neighbour_requests + 1)
    async with httpx.AsyncClient(base_url=args.url, headers=headers, timeout=args.timeout,
                                 limits=limits) as client:
        session_id = None
        for body in views:
            payload = body if session_id is None else {**body, "session_id": session_id}
            r = await client.post("/views", json=payload)
            r.raise_for_status()
            session_id = r.json()["session_id"]
        asked = itertools.count()

        async def keep_asking() -> None:
            while True:
                params = {"session_id": session_id, "n_candidates": 65 + next(asked) % 400,
                          "verify": args.neighbour_verify}
                await _timed(client, tally, NEIGHBOUR, "GET", "/grasp", params=params)

        tasks = [asyncio.create_task(keep_asking()) for _ in range(args.neighbour_requests)]
        started.set()
        try:
            await asyncio.gather(*tasks)
        finally:
            for task in tasks:
                task.cancel()
            with contextlib.suppress(Exception):
                await client.delete(f"/sessions/{session_id}")


async def run(args, scenes: list[list[dict]]) -> Tally:
    import httpx

    tally = Tally()
    neighbour = None
    if args.neighbour_token:
        started = asyncio.Event()
        neighbour = asyncio.create_task(_neighbour(args, scenes[0], tally, started))
        await asyncio.wait([neighbour, asyncio.create_task(started.wait())],
                           return_when=asyncio.FIRST_COMPLETED)
        if neighbour.done():
            neighbour.result()  # its session failed: say why
        await asyncio.sleep(args.neighbour_head_start)
    headers = {"Authorization": f"Bearer {args.token}"} if args.token else {}
    limits = httpx.Limits(max_connections=args.concurrency)
    semaphore = asyncio.Semaphore(args.concurrency)
    async with httpx.AsyncClient(
        base_url=args.url, headers=headers, timeout=args.timeout, limits=limits
    ) as client:
        (await client.get("/healthz")).raise_for_status()

        async def one(i: int) -> None:
            async with semaphore:
                await _session(client, tally, scenes[i % len(scenes)], args)

        try:
            await asyncio.wait_for(
                asyncio.gather(*(one(i) for i in range(args.sessions))), timeout=args.deadline
            )
        finally:
            if neighbour is not None:
                neighbour.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await neighbour
    return tally


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        formatter_class=HelpWithDefaults,
        prog="python -m service.load", description=__doc__.split("\n")[0],
    )
    p.add_argument("--url", default="http://127.0.0.1:8000", help="server on a loopback address")
    p.add_argument("--sessions", type=int, default=32)
    p.add_argument("--views", type=int, default=12, help="views per session (at least 2)")
    p.add_argument("--concurrency", type=int, default=8, help="sessions streaming at once")
    p.add_argument("--scenes", type=int, default=4, help="distinct simulated scenes, cycled")
    p.add_argument("--condition", choices=("camera_pan", "tabletop", "clutter"),
                   default="camera_pan",
                   help="the scenes: objects floating (camera_pan) or resting on a table whose "
                   "plane each session is given with its first view (tabletop), or among 2-5 "
                   "other objects there, sent with label images (clutter: the evaluation's "
                   "clutter scenes; their neighbours become obstacles)")
    p.add_argument("--n-candidates", type=int, default=64, help="GET /grasp n_candidates")
    p.add_argument("--verify", type=int, default=None,
                   help="GET /grasp verify: grasps lift-tested before the answer (default: the "
                   "service's GRASP_VERIFY)")
    p.add_argument(
        "--grasp-every-view",
        action="store_true",
        help="GET /grasp after every view that shows the object (a robot's loop), not only "
        "after the last",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--timeout", type=float, default=300.0, help="seconds per request")
    p.add_argument("--deadline", type=float, default=1800.0, help="seconds for the whole run")
    p.add_argument("--token", default=os.environ.get("GRASP_TOKEN"), help="default $GRASP_TOKEN")
    p.add_argument("--keep", action="store_true", help="keep the sessions (default: delete)")
    p.add_argument("--neighbour-token", help="another client's token: it keeps verified GET "
                   "/grasp going on a session of its own meanwhile (default: no neighbour)")
    p.add_argument("--neighbour-requests", type=int, default=8,
                   help="the neighbour's GET /grasp at a time")
    p.add_argument("--neighbour-verify", type=int, default=8, help="the neighbour's verify")
    p.add_argument("--neighbour-head-start", type=float, default=2.0,
                   help="seconds the neighbour runs before the measured sessions start")
    p.add_argument("--json", help="also write the summary to this file (default: none)")
    args = p.parse_args(argv)
    try:
        args.url = check_loopback(args.url)
    except ValueError as exc:
        p.error(str(exc))
    if args.verify is not None and args.verify < 0:
        p.error(f"--verify must be >= 0, got {args.verify}")
    checked = ("sessions", "views", "concurrency", "scenes", "n_candidates", "neighbour_requests")
    for name in checked:
        if getattr(args, name) < (2 if name == "views" else 1):
            p.error(f"--{name.replace('_', '-')} is too small: {getattr(args, name)}")

    print(f"rendering {args.scenes} scenes × {args.views} views …", flush=True)
    scenes = make_bodies(min(args.scenes, args.sessions), args.views, args.seed, args.condition)
    print(
        f"{args.sessions} sessions × {args.views} views against {args.url} "
        f"({args.concurrency} at a time, n_candidates={args.n_candidates})",
        flush=True,
    )
    import httpx

    start = time.perf_counter()
    try:
        tally = asyncio.run(run(args, scenes))
    except TimeoutError:
        print(f"stopped: the run exceeded --deadline {args.deadline:g} s", file=sys.stderr)
        return 2
    except httpx.HTTPError as exc:
        print(f"no service answers GET {args.url}/healthz: {exc}", file=sys.stderr)
        return 2
    wall = time.perf_counter() - start
    summary = tally.summary() | {"wall_s": round(wall, 2)}
    _print(summary)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(summary, f, indent=2)
    failed = any(r["errors"] for name, r in summary["routes"].items() if name != NEIGHBOUR)
    return 1 if failed or tally.views_lost or tally.bad_indices else 0


def _print(summary: dict) -> None:
    print(f"\n{'route':<24}{'requests':>9}{'p50 ms':>10}{'p99 ms':>10}{'max ms':>10}{'errors':>8}")
    for route, r in summary["routes"].items():
        cells = [r["p50_ms"], r["p99_ms"], r["max_ms"]]
        shown = "".join(f"{'-' if c is None else f'{c:.1f}':>10}" for c in cells)
        print(f"{route:<24}{r['requests']:>9}{shown}{r['errors']:>8}")
    if summary["grasp_timing_ms"]:
        split = ", ".join(
            f"{k} {v['p50_ms']:.1f}/{v['p99_ms']:.1f}"
            for k, v in summary["grasp_timing_ms"].items()
        )
        print(f"\nGET /grasp server-side split, p50/p99 ms: {split}")
    print(
        f"views sent {summary['views_sent']}, lost {summary['views_lost']}, sessions with "
        f"out-of-order indices {summary['out_of_order_view_indices']}, wall {summary['wall_s']} s"
    )
    for route, samples in summary["error_samples"].items():
        print(f"errors on {route}: {samples}")


if __name__ == "__main__":
    sys.exit(main())
