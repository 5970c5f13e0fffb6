"""Values kept by key in a process, the few most recently asked: a planner's repeated work on the
same arrays (a feature's patch, a placed mesh, a camera pose's bodies), whose keys are the bytes
of what makes them, so functools.lru_cache (hashable arguments) cannot hold them."""
from __future__ import annotations

from typing import Callable, Generic, Hashable, TypeVar

V = TypeVar("V")


class Recent(Generic[V]):
    """At most `most` values by key, the least recently asked dropped first."""

    def __init__(self, most: int) -> None:
        self.most = most
        self._kept: dict[Hashable, V] = {}

    def get(self, key: Hashable, make: Callable[[], V]) -> V:
        """The value kept for `key`, else make()'s, kept; either way the most recent now."""
        value = self._kept.pop(key) if key in self._kept else make()
        self._kept[key] = value
        while len(self._kept) > self.most:
            self._kept.pop(next(iter(self._kept)))
        return value

    def __len__(self) -> int:
        return len(self._kept)

    def clear(self) -> None:
        self._kept.clear()
