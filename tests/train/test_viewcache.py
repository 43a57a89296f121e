"""The planned view cache: every request gets its own key's value, under any budget, with the loader thread
running ahead; the budget is never exceeded; eviction follows the plan."""

from __future__ import annotations

import random
import threading
import time

import pytest

from stgs.errors import StgsError
from stgs.train.viewcache import PlannedCache


def loader(log: list, delay: float = 0.0):
    def load(key):
        if delay:
            time.sleep(delay)
        log.append(key)
        return ("value", key)
    return load


@pytest.mark.parametrize("budget", [0, 3, 10, 40, 1000])
def test_every_request_gets_its_own_value_and_the_budget_holds(budget):
    rng = random.Random(budget)
    sizes = {k: 1 + k % 4 for k in range(70)}
    plan = [rng.randrange(60) for _ in range(2000)]
    log: list = []
    cache = PlannedCache(loader(log), sizes.__getitem__, budget, look_ahead=16)
    cache.plan(plan)
    for i, key in enumerate(plan):
        assert cache.get(key) == ("value", key), i
        if i % 97 == 0:  # a request outside the plan (validation's) between planned ones
            other = rng.randrange(60, 70)
            assert cache.get(other) == ("value", other)
        assert cache.used <= budget
    assert cache.peak <= budget
    cache.close()
    if budget >= sum(sizes.values()):  # everything fits: each planned key is loaded once
        assert len([k for k in log if k < 60]) == len(set(plan))
    elif budget == 0:  # nothing is held: every request loads
        assert len(log) == len(plan) + len(plan) // 97 + 1


def test_eviction_keeps_what_is_used_soonest():
    """With room for two, the plan a b c a b c ... reloads only the entry Belady's rule gives up."""
    log: list = []
    cache = PlannedCache(loader(log), lambda k: 1, 2, look_ahead=1)
    plan = list("abcabcabc")
    cache.plan(plan)
    assert [cache.get(k)[1] for k in plan] == plan
    # Belady: 3 first loads, then one miss per two requests instead of LRU's miss on every request
    assert len(log) == 6


def test_a_large_budget_loads_each_view_once_and_ahead_of_the_consumer():
    log: list = []
    cache = PlannedCache(loader(log, delay=0.001), lambda k: 1, 100)
    plan = [k % 10 for k in range(200)]
    cache.plan(plan)
    time.sleep(0.2)
    assert len(log) == 10  # loaded ahead, before any request
    for key in plan:
        cache.get(key)
    assert len(log) == 10 and cache.loads == 10


def test_a_new_plan_replaces_the_old_and_keeps_what_is_held():
    log: list = []
    cache = PlannedCache(loader(log), lambda k: 1, 3)
    cache.plan([1, 2, 3, 1])
    assert cache.get(1) == ("value", 1)
    cache.plan([3, 2, 9])
    assert [cache.get(k)[1] for k in (3, 2, 9)] == [3, 2, 9]
    assert log.count(2) == 1 and log.count(3) == 1


def test_a_loader_error_reaches_the_consumer_and_a_bad_budget_is_refused():
    def load(key):
        if key == 3:
            raise StgsError("view 3 is unreadable")
        return key

    cache = PlannedCache(load, lambda k: 1, 2)
    cache.plan([1, 2, 3, 4])
    assert cache.get(1) == 1 and cache.get(2) == 2
    with pytest.raises(StgsError, match="view 3"):
        cache.get(3)
    cache.close()
    with pytest.raises(StgsError, match="budget"):
        PlannedCache(load, lambda k: 1, -1)


def test_requests_from_two_threads_are_served_correctly():
    cache = PlannedCache(loader([]), lambda k: 2, 7, look_ahead=4)
    plan = [i % 13 for i in range(500)]
    cache.plan(plan)
    errors = []

    def outside():
        for i in range(300):
            if cache.get(100 + i % 5) != ("value", 100 + i % 5):
                errors.append(i)

    thread = threading.Thread(target=outside)
    thread.start()
    for key in plan:
        assert cache.get(key) == ("value", key)
    thread.join()
    assert not errors and cache.peak <= 7
