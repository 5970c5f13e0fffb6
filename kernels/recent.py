"""Values kept by key in a process, the few most recently asked, each made under a lock: work
built from the same arrays again and again (a part's BVH, a lamp's and a material's kernel
arrays; the planner's memos: a feature's patch, a placed mesh, a camera pose's bodies), whose
keys are the bytes of what makes them, so functools.lru_cache (hashable arguments) cannot hold
them, asked from several threads of one process (runtime.in_background: a judged column's patches
are laid while the plan before it runs)."""
import threading
from typing import Callable, Generic, Hashable, TypeVar

V = TypeVar("V")


class Kept(Generic[V]):
    """At most `most` values by key, the least recently asked dropped first; get() is atomic
    (make() runs under the lock: two threads asking one key make it once)."""

    def __init__(self, most: int) -> None:
        self.most = most
        self._kept: dict[Hashable, V] = {}
        self._lock = threading.Lock()

    def get(self, key: Hashable, make: Callable[[], V]) -> V:
        """The value kept for `key`, else make()'s, kept; either way the most recent now."""
        with self._lock:
            value = self._kept.pop(key) if key in self._kept else make()
            self._kept[key] = value
            while len(self._kept) > self.most:
                self._kept.pop(next(iter(self._kept)))
            return value

    def __len__(self) -> int:
        return len(self._kept)

    def clear(self) -> None:
        with self._lock:
            self._kept.clear()
