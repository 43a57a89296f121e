"""A byte-bounded cache that loads ahead along a known plan of requests, in a background thread.

Training draws its views from a schedule fixed before the stage starts (stgs.train.images.view_draws), so the
cache knows every future request: a loader thread walks the plan ahead of the consumer and loads what is not
held, and when the budget is full it evicts the entry whose next planned use is furthest away (Belady's rule,
optimal for a known sequence). An entry planned between the consumer and the loader is never evicted, so the
loader waits for the consumer rather than throw away what is about to be used. A request outside the plan
(validation's spread of views) is loaded by the caller and kept only where the budget has room.

What a request returns does not depend on the budget, only how often it is loaded: the same plan gives the
same values under any budget, which is what keeps a run's bytes independent of --max-memory.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable, Sequence
from typing import Generic, TypeVar

from stgs.errors import StgsError

K = TypeVar("K", bound=Hashable)
V = TypeVar("V")
NEVER = 1 << 62
"""The next use of an entry the plan does not request again."""
LOOK_AHEAD = 256
"""Planned requests the loader may run ahead of the consumer."""


class PlannedCache(Generic[K, V]):
    """`load(key)` values within `budget` bytes (`size(key)` each, known before loading)."""

    def __init__(self, load: Callable[[K], V], size: Callable[[K], int], budget: int, look_ahead: int = LOOK_AHEAD):
        if budget < 0:
            raise StgsError(f"view cache: budget must be >= 0 bytes, got {budget}")
        self._load, self._size, self.budget, self._look_ahead = load, size, budget, look_ahead
        self._entries: dict[K, V] = {}
        self._next: dict[K, int] = {}
        """Each held entry's next planned use (NEVER: none)."""
        self.used = 0
        self.peak = 0
        self.loads = 0
        self._plan: list[K] = []
        self._next_use: list[int] = []
        self._pos = self._ahead = 0
        self._error: BaseException | None = None
        self._cond = threading.Condition()
        self._thread: threading.Thread | None = None
        self._stop = False

    # --- the plan ---

    def plan(self, keys: Sequence[K]) -> None:
        """The requests to come, in order (replaces any earlier plan)."""
        self._halt()
        keys = list(keys)
        following: dict[K, int] = {}
        next_use = [NEVER] * len(keys)
        for i in range(len(keys) - 1, -1, -1):
            next_use[i] = following.get(keys[i], NEVER)
            following[keys[i]] = i
        with self._cond:
            self._plan, self._next_use, self._pos, self._ahead = keys, next_use, 0, 0
            self._next = {k: following.get(k, NEVER) for k in self._entries}
            self._error, self._stop = None, False
        if keys:
            self._thread = threading.Thread(target=self._run, name="view-cache", daemon=True)
            self._thread.start()

    def close(self) -> None:
        """Stop the loader and drop every entry."""
        self._halt()
        with self._cond:
            self._entries.clear()
            self._next.clear()
            self.used = 0

    def _halt(self) -> None:
        with self._cond:
            self._stop = True
            self._cond.notify_all()
        if self._thread is not None:
            self._thread.join()
            self._thread = None

    # --- requests ---

    def get(self, key: K) -> V:
        """`key`'s value: the plan's next request waits for the loader; any other is loaded here if not held."""
        with self._cond:
            planned = self._pos < len(self._plan) and self._plan[self._pos] == key
            if planned:
                oversized = self._size(key) > self.budget  # the loader skips it: loaded here, never held
                while not oversized and key not in self._entries and self._error is None:
                    self._cond.wait()
                if self._error is not None:
                    raise self._error
                self._pos += 1
                self._cond.notify_all()
                if not oversized:
                    self._next[key] = self._next_use[self._pos - 1]
                    return self._entries[key]
            elif key in self._entries:
                return self._entries[key]
        value = self._load(key)
        with self._cond:
            if key not in self._entries and self._make_room(self._size(key), self._ahead):
                self._insert(key, value, NEVER)
        return value

    def __contains__(self, key: K) -> bool:
        with self._cond:
            return key in self._entries

    # --- the loader thread ---

    def _run(self) -> None:
        try:
            while True:
                with self._cond:
                    key = self._claim()
                    if key is None:
                        return
                value = self._load(key)
                with self._cond:
                    self.used -= self._size(key)  # the reservation becomes the entry
                    if key in self._entries:  # a request outside the plan loaded it meanwhile
                        self._next[key] = min(self._next[key], self._ahead)
                    else:
                        self._insert(key, value, self._ahead)
                    self._ahead += 1
                    self._cond.notify_all()
        except BaseException as exc:  # handed to the consumer, which raises it on its next request
            with self._cond:
                self._error = exc
                self._cond.notify_all()

    def _claim(self) -> K | None:
        """The next planned key to load, once there is room for it (None: stop). Called holding the lock."""
        while True:
            if self._stop or self._ahead >= len(self._plan):
                return None
            key = self._plan[self._ahead]
            if key in self._entries:
                self._next[key] = min(self._next.get(key, NEVER), self._ahead)
                self._ahead += 1
                continue
            size = self._size(key)
            if size > self.budget:
                self._ahead += 1
                continue
            if self._ahead - self._pos < self._look_ahead and self._make_room(size, self._ahead):
                self.used += size  # reserved while it loads, outside the lock
                return key
            self._cond.wait()

    def _make_room(self, size: int, horizon: int) -> bool:
        """Evict, furthest next use first, entries not planned before `horizon` until `size` more bytes fit;
        False (nothing evicted) when they cannot. Called holding the lock."""
        if size > self.budget:
            return False
        victims, free = [], self.budget - self.used
        for key in sorted(self._entries, key=lambda k: self._next[k], reverse=True):
            if free >= size or self._next[key] <= horizon:
                break
            victims.append(key)
            free += self._size(key)
        if free < size:
            return False
        for key in victims:
            del self._entries[key], self._next[key]
            self.used -= self._size(key)
        return True

    def _insert(self, key: K, value: V, next_use: int) -> None:
        self._entries[key] = value
        self._next[key] = next_use
        self.used += self._size(key)
        self.peak = max(self.peak, self.used)
        self.loads += 1
