"""Fair planners (service.engine.planning): a free worker goes to the waiting clients in turn,
and one client cannot hold more than its share of the queue."""

from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from service.engine import planning


def test_a_freed_slot_goes_to_the_next_client_in_turn():
    """One slot; client a queues three calls, then b one: b's comes second, not fourth."""
    order = []

    async def scenario():
        slots = planning.FairSlots(1)

        async def call(client, name):
            async with slots.take(client):
                order.append(name)
                await asyncio.sleep(0.01)

        tasks = [asyncio.create_task(call("a", f"a{i}")) for i in range(4)]
        await asyncio.sleep(0)  # a0 runs, a1-a3 wait
        tasks.append(asyncio.create_task(call("b", "b0")))
        await asyncio.gather(*tasks)
        assert slots.free == 1 and not slots._waiting

    asyncio.run(scenario())
    assert order == ["a0", "a1", "b0", "a2", "a3"]


def test_a_cancelled_waiter_gives_its_turn_on():
    async def scenario():
        slots = planning.FairSlots(1)
        held = asyncio.Event()
        release = asyncio.Event()

        async def holder():
            async with slots.take("a"):
                held.set()
                await release.wait()

        first = asyncio.create_task(holder())
        await held.wait()
        waiting = asyncio.create_task(slots.take("b").__aenter__())
        await asyncio.sleep(0)
        waiting.cancel()
        with pytest.raises(asyncio.CancelledError):
            await waiting
        release.set()
        await first
        assert slots.free == 1 and not slots._waiting  # nothing lost, nobody left waiting

    asyncio.run(scenario())


def test_one_client_is_refused_beyond_its_share_while_others_are_admitted(monkeypatch):
    def slow_plan(request):
        time.sleep(0.2)
        return [], 0.2

    monkeypatch.setattr(planning, "plan_grasps", slow_plan)
    mesh = (np.zeros((3, 3)), np.array([[0, 1, 2]]))

    def asked(n):
        return planning.PlanRequest(*mesh, n_candidates=n, seed=0, top_k=1)

    async def scenario():
        planner = planning.Planner(1, processes=False, queue=8, cache=0, per_client=2)
        mine = [asyncio.create_task(planner.plan(asked(n), client="a")) for n in (1, 2)]
        await asyncio.sleep(0.05)
        with pytest.raises(planning.PlannerBusy, match="GRASP_CLIENT_PLANS"):
            await planner.plan(asked(3), client="a")
        _, _, cached = await planner.plan(asked(3), client="b")  # b is still admitted
        await asyncio.gather(*mine)
        assert not cached and planner.pending == 0

    asyncio.run(scenario())


def test_one_clients_trials_leave_a_worker_for_another_clients_plan(monkeypatch):
    """Two workers, trials_per_client=1: client a's six lift trials run one at a time, and b's
    plan, asked while they run, starts at once on the other worker."""
    running, most, started = [], [0], {}

    def trial(name):
        running.append(name)
        most[0] = max(most[0], sum(r.startswith("a") for r in running))
        time.sleep(0.05)
        running.remove(name)

    def slow_plan(request):
        started["b"] = time.perf_counter()
        return [], 0.0

    monkeypatch.setattr(planning, "plan_grasps", slow_plan)

    async def scenario():
        planner = planning.Planner(2, processes=False, queue=8, cache=0, trials_per_client=1)
        trials = [asyncio.create_task(planner._trial(lambda i=i: trial(f"a{i}"), "a"))
                  for i in range(6)]
        await asyncio.sleep(0.02)
        asked = time.perf_counter()
        await planner.plan(planning.PlanRequest(np.zeros((3, 3)), np.array([[0, 1, 2]]),
                                                n_candidates=4, seed=0, top_k=1), client="b")
        await asyncio.gather(*trials)
        assert not planner._trial_gates
        return started["b"] - asked

    waited = asyncio.run(scenario())
    assert most[0] == 1 and waited < 0.04, (most, waited)
