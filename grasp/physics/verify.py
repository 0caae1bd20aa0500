"""Grasps tried in physics before they are returned: the planner's verification.

``plan(..., verify=N)`` (:mod:`grasp.planner`) lift-tests its best-ranked grasps **on the mesh it
planned on** (a completion in the service and the evaluation's completion rows, never the true
object), standing on the support plane it was given, with a mass estimated from that mesh. Each
grasp faces the same :data:`TRIALS` perturbed trials (:func:`trials`): the density, the hand's
friction and the shake directions drawn from stated ranges (:class:`VerifySettings`), seeded by
the plan's seed and a stream of their own, so that no trial repeats a referee's shake.

The grasps are tried in the ranking's order, force-closure grasps only (those the lift model
expects to drop included), until one holds in every trial or ``N`` were tried. The answer's order
(:func:`order`): the grasps that held in every trial, then the other successes, those not tried
(in the ranking's order) before those seen to drop (most trials held first), then the failures.
A force-closure grasp the lift model expected to drop but that held in every trial becomes a
success. Each grasp carries what its verification saw (:class:`grasp_client.wire.Verification`,
the type that travels).

The work is split so that the service can spread one grasp's trials over its planner processes
and interleave them with other sessions' plans (:mod:`service.engine.planning`): :func:`eligible`
(which grasps may be tried), :func:`trials`, :func:`run_trial` (one lift test, picklable inputs),
:func:`verdict` (a grasp's trials summed up) and :func:`order`. :func:`verify` is the same loop,
serial, for ``plan``.

This module must not import torch (docs/design.md §2).
"""

from __future__ import annotations

import dataclasses
import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass

import numpy as np
import trimesh

from grasp.hand.result import GraspResult
from grasp.physics.settings import DENSITY_KG_M3
from grasp_client.wire import SupportPlane, Verification

#: Lift trials per verified grasp (chosen on training-split objects: docs/grasping.md).
TRIALS = 2


@dataclass(frozen=True)
class VerifySettings:
    """How a planned grasp is tried (every range is closed; SI units).

    ``density``: kg/m³ of the planned mesh (the planner does not know the true mass; the lift
    test's and the lift model's :data:`grasp.physics.settings.DENSITY_KG_M3`). Each trial multiplies
    it by a factor drawn log-uniformly from ``mass_factor`` and draws the hand–object friction μ
    uniformly from ``friction``; its shake directions come from a seed of the trial's own stream.
    """

    trials: int = TRIALS
    density: float = DENSITY_KG_M3
    mass_factor: tuple[float, float] = (0.8, 1.25)
    friction: tuple[float, float] = (0.8, 1.0)

    def __post_init__(self) -> None:
        if self.trials < 1:
            raise ValueError(f"verification needs at least 1 trial, got {self.trials}")
        lo, hi = self.mass_factor
        f_lo, f_hi = self.friction
        if not (self.density > 0 and 0 < lo <= hi and 0 <= f_lo <= f_hi):
            raise ValueError(f"VerifySettings: density > 0, 0 < mass_factor[0] <= [1], "
                             f"0 <= friction[0] <= [1]; got {self}")


DEFAULT_VERIFY = VerifySettings()


@dataclass(frozen=True)
class Trial:
    """One perturbed lift test: its index, the object's density (kg/m³), the hand's friction
    and the seed of its shake directions."""

    index: int
    density: float
    friction: float
    seed: int


@dataclass(frozen=True)
class Outcome:
    """What one trial saw: held, and the lift test's reason."""

    held: bool
    reason: str


NOT_TRIED = Verification(tried=False)


def trials(seed: int, settings: VerifySettings = DEFAULT_VERIFY) -> list[Trial]:
    """The ``settings.trials`` perturbed trials of a plan with ``seed`` (every grasp of the plan
    faces the same ones), drawn from a stream of their own."""
    rng = np.random.default_rng([seed, zlib.crc32(b"grasp/physics/verify")])
    lo, hi = np.log(settings.mass_factor)
    out = []
    for index in range(settings.trials):
        factor = float(np.exp(rng.uniform(lo, hi)))
        friction = float(rng.uniform(*settings.friction))
        out.append(Trial(index, settings.density * factor, friction,
                         int(rng.integers(2**31 - 1))))
    return out


def eligible(grasp: GraspResult) -> bool:
    """Whether a ranked grasp may be tried: it has force closure (a success, or one the lift
    model expects to drop)."""
    return grasp.epsilon > 0.0 and bool(grasp.contacts)


def run_trial(mesh: trimesh.Trimesh, grasp: GraspResult, support_plane: SupportPlane | None,
              trial: Trial) -> Outcome:
    """One lift test of ``grasp`` on ``mesh`` as a robot executes it (guarded approach), the
    object standing on ``support_plane`` (floating without one). A mesh the lift test refuses
    (not resting on the plane, say) is a drop that says why."""
    from completion.bullet import quiet_fds
    from grasp.physics.lift import lift_test

    try:
        with quiet_fds(1):
            r = lift_test(mesh, grasp, seed=trial.seed, friction=trial.friction,
                          density=trial.density, support_plane=support_plane,
                          approach="guarded")
    except ValueError as exc:
        return Outcome(False, f"not lift-tested: {exc}")
    return Outcome(bool(r.success), r.reason)


def verdict(outcomes: Sequence[Outcome]) -> Verification:
    """A grasp's trials summed up."""
    drops = [o.reason for o in outcomes if not o.held]
    return Verification(True, len(outcomes), len(outcomes) - len(drops),
                        drops[0] if drops else None)


def order(ranked: Sequence[GraspResult], seen: dict[int, Verification]) -> list[GraspResult]:
    """``ranked`` with each grasp's verification (``seen``: index in ``ranked`` → what its trials
    saw; the others were not tried), reordered: held in every trial; then the other successes,
    those not tried before those seen to drop (most trials held first); then the failures; each
    group in the ranking's order. A force-closure grasp that held in every trial is a success
    whatever the lift model said."""
    out = []
    for i, g in enumerate(ranked):
        v = seen.get(i, NOT_TRIED)
        if v.held_all and not g.success:
            p = g.hold_probability
            g = dataclasses.replace(g, success=True, reason=(
                f"force closure; held in every lift trial ({v.held}/{v.trials}) though the lift "
                f"model gave it {p:.2f}"))
        out.append(dataclasses.replace(g, verification=v))

    def key(i: int) -> tuple:
        g, v = out[i], out[i].verification
        dropped = v.tried and not v.held_all
        return (not v.held_all, not g.success, dropped, -v.held / v.trials if v.tried else 0.0, i)

    return [out[i] for i in sorted(range(len(out)), key=key)]


def verify(
    mesh: trimesh.Trimesh,
    ranked: Sequence[GraspResult],
    n: int,
    support_plane: SupportPlane | None,
    seed: int,
    settings: VerifySettings = DEFAULT_VERIFY,
    run: Callable[[Iterable], Iterable[Outcome]] | None = None,
) -> list[GraspResult]:
    """Try the first ``n`` eligible grasps of ``ranked`` (distinct, best first) until one holds
    in every trial; the grasps reordered by :func:`order`. ``run`` maps an iterable of
    ``(mesh, grasp, plane, trial)`` to outcomes (default: one after another in this process)."""
    if n < 0:
        raise ValueError(f"verify must be >= 0 grasps to try, got {n}")
    if run is None:
        def run(jobs):
            return [run_trial(*job) for job in jobs]
    plan_trials = trials(seed, settings)
    seen: dict[int, Verification] = {}
    for i, g in enumerate(ranked):
        if len(seen) >= n:
            break
        if not eligible(g):
            continue
        seen[i] = verdict(list(run([(mesh, g, support_plane, t) for t in plan_trials])))
        if seen[i].held_all:
            break
    return order(ranked, seen)


def describe(v: Verification | None) -> str:
    """A verification in words."""
    if v is None:
        return "not verified"
    if not v.tried:
        return "not tried"
    text = f"held {v.held}/{v.trials} lift trials"
    return text if v.first_drop is None else f"{text}; first drop: {v.first_drop}"


__all__ = ["DEFAULT_VERIFY", "NOT_TRIED", "TRIALS", "Outcome", "Trial", "Verification",
           "VerifySettings", "describe", "eligible", "order", "run_trial", "trials", "verdict",
           "verify"]
