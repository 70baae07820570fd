"""A cache of values bounded by their total size in bytes, shared by the tile endpoints."""

from __future__ import annotations

import threading
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

Value = TypeVar("Value")


class BoundedCache(Generic[Value]):
    """Values by key, up to `limit_bytes` in all as measured by `size`; when full it starts over,
    since a viewer's working set is far smaller. Keys name a specimen by (id, version), so a
    rebuilt specimen is never answered from an older build. Thread-safe."""

    def __init__(self, limit_bytes: int, size: Callable[[Value], int]):
        self._values: dict[Hashable, Value] = {}
        self._total_bytes = 0
        self._limit_bytes = limit_bytes
        self._size = size
        self._lock = threading.Lock()

    def cached(self, key: Hashable) -> Value | None:
        with self._lock:
            return self._values.get(key)

    def get(self, key: Hashable, produce: Callable[[], Value]) -> Value:
        """The cached value, or `produce()`'s, kept for next time."""
        value = self.cached(key)
        if value is None:
            value = produce()
            size = self._size(value)
            with self._lock:
                if self._total_bytes + size > self._limit_bytes:
                    self._values.clear()
                    self._total_bytes = 0
                if key not in self._values:
                    self._values[key] = value
                    self._total_bytes += size
        return value

    @property
    def total_bytes(self) -> int:
        return self._total_bytes
