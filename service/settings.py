"""Service settings: one pydantic-settings class, read from ``GRASP_*`` environment variables."""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import TYPE_CHECKING

from pydantic import Field, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from grasp.defaults import AUTOGRASP_BUDGET

if TYPE_CHECKING:
    from service.intake.frames import FrameChecks
    from service.intake.inputs import DecodeLimits


#: Idempotent answers kept per client (``GRASP_MAX_ANSWERS``): beyond it the oldest go, so a client
#: that sends a new key with every view cannot fill the store.
MAX_ANSWERS = 10_000


class Settings(BaseSettings):
    """Every knob of the service; ``GRASP_<NAME>`` sets ``<name>`` (e.g. ``GRASP_PORT=8080``)."""

    model_config = SettingsConfigDict(env_prefix="GRASP_", frozen=True)

    host: str = Field("127.0.0.1", description="interface uvicorn binds to")
    port: int = Field(8000, ge=0, le=65535, description="TCP port (0 = any free port)")
    model: str = Field(
        "mvp", description="shipped weights name (completion/weights/<name>.pt) or checkpoint path"
    )
    store_path: Path = Field(
        Path("grasp_store.sqlite"), description="SQLite file holding the sessions"
    )
    store_url: str | None = Field(
        None,
        pattern=r"^(redis|rediss|unix)://",
        description="redis://host:port/db puts the sessions in Redis, shared by every replica "
        "on that URL (unset: the SQLite store_path)",
    )
    max_sessions: int = Field(1000, ge=1, description="sessions kept at most; more get 503")
    session_ttl_s: float = Field(
        3600.0, gt=0, description="a session idle for longer than this is deleted"
    )
    unseen_session_ttl_s: float = Field(
        60.0,
        gt=0,
        description="a session whose views never showed the object is deleted this long after "
        "its last view (it cannot answer yet; keeps empty sessions from filling the store)",
    )
    lock_lease_s: float = Field(
        5.0,
        gt=0,
        le=300,
        description="with store_url: a replica holds a session's lock for this long, renewed "
        "while it applies a view; one that dies holding it blocks that session this long at "
        "most (a view waits up to two leases for the lock, then gets 503 with Retry-After)",
    )
    max_image_pixels: int = Field(
        2048 * 2048, ge=1, description="largest depth image (width × height) accepted"
    )
    max_points: int = Field(
        500_000,
        ge=1,
        description="most points in one view: more sent as points get 422; a depth image with "
        "more object pixels is thinned to every s-th pixel along both axes (a lower resolution "
        "of the same camera) before any point is made",
    )
    max_parsing: int = Field(2, ge=1, description="view bodies decoded at once (more wait)")
    body_memory_bytes: int = Field(
        64 * 1024 * 1024, ge=1024 * 1024, description="bytes of POST /views bodies held at once "
        "(each reserves 2 × its Content-Length before it is read); more wait, then get 503"
    )
    decode_memory_bytes: int = Field(
        96 * 1024 * 1024, ge=1024 * 1024, description="bytes the decoding of views may hold at "
        "once (a depth image reserves 24 bytes a pixel it declares, JSON 400 bytes an array, "
        "before it is decoded); more wait, then get 503"
    )
    memory_wait_s: float = Field(
        30.0, gt=0, description="how long a view waits for memory (body_memory_bytes, "
        "decode_memory_bytes) before 503 with Retry-After"
    )
    max_views: int = Field(
        1000,
        ge=1,
        description="most views a session keeps when the model's state grows with each view "
        "(MVT's key/value cache); MVP's state has a fixed size and is not capped",
    )
    max_body_bytes: int = Field(
        32 * 1024 * 1024, ge=1024, description="largest request body; larger ones get 413"
    )
    max_head_bytes: int = Field(
        16 * 1024, ge=1024, le=1024 * 1024, description="largest request line and headers "
        "together; a longer URL gets 414, longer headers 431"
    )
    header_timeout_s: float = Field(
        10.0,
        gt=0,
        description="a request's line and headers must arrive within this long of the "
        "connection opening (or of the previous answer); a slower client gets 408 and is "
        "disconnected",
    )
    body_timeout_s: float = Field(
        60.0,
        gt=0,
        description="a request body must arrive within this long of its headers (a 32 MB body "
        "needs 0.6 MB/s); a slower client is disconnected",
    )
    max_connections_per_client: int = Field(
        64,
        ge=1,
        description="open connections from one client at most; more get 429 and are closed. A "
        "client is its address, or, once a request names it, its token (when GRASP_TOKEN lists "
        "several) or the address a trusted proxy forwards (GRASP_TRUSTED_PROXIES)",
    )
    token: SecretStr | None = Field(
        None, description="if set, every route but /healthz needs 'Authorization: Bearer "
        "<token>'; several tokens separated by commas (one per client) are each accepted, and "
        "each gets its own connection cap"
    )
    trusted_proxies: str = Field(
        "", description="comma-separated addresses of reverse proxies whose X-Forwarded-For "
        "names the client (its last address not itself a proxy); empty: the header is ignored"
    )
    n_candidates: int = Field(64, ge=1, description="default grasp candidates per GET /grasp")
    max_candidates: int = Field(512, ge=1, description="largest n_candidates a client may ask")
    max_depth_median_m: float = Field(
        5.0, gt=0, description="a depth image whose median over the object is farther (m) is "
        "refused: millimetres sent as metres"
    )
    max_point_distance_m: float = Field(
        10.0, gt=0, description="views whose object points lie farther from the camera (m) are "
        "refused: millimetres sent as metres, or a point cloud in another unit"
    )
    registered: bool = Field(
        True, description="sessions fuse their posed views in the world frame (the object taken "
        "as still: completion/evidence.py); false: MVP alone, as for views without camera_pose. "
        "A view's registered field sets it per session"
    )
    check_frames: bool = Field(
        True, description="check each posed view's camera_pose and support_plane against what it "
        "shows (service/intake/frames.py): a contradiction is a 422 naming the likely mistake"
    )
    max_camera_distance_m: float = Field(
        20.0, gt=0, description="a camera_pose farther from the world's origin, or a camera that "
        "moved farther between views (m), is refused"
    )
    plane_tolerance_m: float = Field(
        0.03, gt=0, description="the camera, and the object's points, may lie this far below the "
        "support plane (m); table pixels within it of the plane count as on it"
    )
    max_plane_gap_m: float = Field(
        0.3, gt=0, description="with no table in view, the object's lowest point may lie this far "
        "above the support plane (m)"
    )
    max_object_jump_m: float = Field(
        0.2, gt=0, description="between views from different poses, the object's points (their "
        "median, world frame) may move this far (m)"
    )
    plan_seed: int = Field(0, description="seed of the grasp planner (same state, same grasp)")
    plan_budget: int = Field(
        AUTOGRASP_BUDGET, ge=1, description="candidates the planner autograsps exactly, the most "
        "promising first (the rest are only screened); the top grasp does not depend on top_k"
    )
    verify: int = Field(
        0, ge=0, description="default of GET /grasp's verify: the best grasps lift-tested on the "
        "completion before the answer, until one holds (0: none; docs/service.md says why)"
    )
    max_verify: int = Field(8, ge=0, description="largest verify a client may ask")
    torch_threads: int = Field(
        1, ge=1, description="torch intra-op threads (torch.set_num_threads)"
    )
    inference_workers: int = Field(
        2, ge=1, description="model steps (POST /views, completions) running at once"
    )
    planning_workers: int = Field(2, ge=1, description="grasp plans running at once")
    planning_queue: int = Field(
        16, ge=0, description="grasp plans waiting for a worker at most; more get 503"
    )
    client_plans: int = Field(
        8, ge=1, description="grasp plans of one client (token) running or waiting at most; "
        "more get 503 while other clients' plans are still admitted. Free workers go to the "
        "waiting clients in turn"
    )
    client_trials: int | None = Field(
        None, ge=1, description="planner workers one client's verification (lift trials) may "
        "hold at once; unset: all but one with several tokens (another client's plan always "
        "finds a worker soon), all of them with one token or none"
    )
    max_answers: int = Field(
        MAX_ANSWERS, ge=1, description="idempotent answers (POST /views with an Idempotency-Key) "
        "kept per client, the oldest dropped beyond it; each lives as long as a session"
    )
    plan_cache: int = Field(
        128, ge=0, description="plans kept for a repeated GET /grasp on an unchanged mesh"
    )
    planning_processes: bool = Field(
        True, description="plan in worker processes (false: in threads of the server process)"
    )

    @field_validator("trusted_proxies")
    @classmethod
    def _addresses(cls, value: str) -> str:
        for part in filter(None, (p.strip() for p in value.split(","))):
            try:
                ipaddress.ip_address(part)
            except ValueError:
                raise ValueError(f"GRASP_TRUSTED_PROXIES: {part!r} is not an IP address "
                                 "(give addresses separated by commas)") from None
        return value

    @field_validator("token")
    @classmethod
    def _tokens(cls, value: SecretStr | None) -> SecretStr | None:
        if value is not None and not all(t.strip() for t in value.get_secret_value().split(",")):
            raise ValueError("GRASP_TOKEN: an empty token (tokens are separated by commas)")
        return value

    def trials_per_client(self) -> int:
        """``client_trials``, or its default for these tokens and workers."""
        if self.client_trials is not None:
            return self.client_trials
        workers = self.planning_workers
        return max(1, workers - 1) if len(self.tokens()) > 1 else workers

    def tokens(self) -> tuple[str, ...]:
        """The accepted bearer tokens (none: no token is needed)."""
        if self.token is None:
            return ()
        return tuple(t.strip() for t in self.token.get_secret_value().split(","))

    def proxies(self) -> frozenset[str]:
        """The trusted proxies' addresses, normalised (``ipaddress``'s spelling)."""
        return frozenset(str(ipaddress.ip_address(p.strip()))
                         for p in self.trusted_proxies.split(",") if p.strip())

    def frame_checks(self) -> FrameChecks | None:
        """The frame checks' tolerances (:mod:`service.intake.frames`; None: GRASP_CHECK_FRAMES
        is off)."""
        from service.intake.frames import FrameChecks

        if not self.check_frames:
            return None
        return FrameChecks(self.max_camera_distance_m, self.plane_tolerance_m,
                           self.max_plane_gap_m, self.max_object_jump_m)

    def decode_limits(self) -> DecodeLimits:
        """What a view may hold (:func:`service.intake.inputs.decode_view`)."""
        from service.intake.inputs import DecodeLimits

        return DecodeLimits(self.max_image_pixels, self.max_points, self.max_depth_median_m,
                            self.max_point_distance_m)

    @model_validator(mode="after")
    def _verify_within_its_maximum(self) -> Settings:
        if self.verify > self.max_verify:
            raise ValueError(f"GRASP_VERIFY ({self.verify}) must be at most GRASP_MAX_VERIFY "
                             f"({self.max_verify})")
        return self
