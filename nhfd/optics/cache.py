"""An explicit, bounded cache of transfer functions.

Callers own a `KernelCache` and pass it in; nothing is cached behind their back. Keys hold every
input that changes a kernel (shape, pitch, wavelengths, depths, band limit, aperture, dtype,
device), so a hit is always the right kernel.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable

import torch


class KernelCache:
    """Least-recently-used map from a kernel key to a tensor, bounded in bytes."""

    def __init__(self, max_bytes: int = 512 * 2**20) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes = {max_bytes}: must be >= 0 (0 disables caching)")
        self.max_bytes = int(max_bytes)
        self._items: OrderedDict[Hashable, torch.Tensor] = OrderedDict()
        self.nbytes = 0
        self.hits = 0
        self.misses = 0

    def __len__(self) -> int:
        return len(self._items)

    def get(self, key: Hashable, compute: Callable[[], torch.Tensor]) -> torch.Tensor:
        """The tensor cached under `key`, else `compute()`, kept when it fits `max_bytes`
        (least recently used entries dropped to make room)."""
        if key in self._items:
            self.hits += 1
            self._items.move_to_end(key)
            return self._items[key]
        self.misses += 1
        value = compute()
        size = value.numel() * value.element_size()
        if size <= self.max_bytes:
            while self._items and self.nbytes + size > self.max_bytes:
                _, old = self._items.popitem(last=False)
                self.nbytes -= old.numel() * old.element_size()
            self._items[key] = value
            self.nbytes += size
        return value

    def clear(self) -> None:
        """Drop every cached tensor (the hit and miss counts stay)."""
        self._items.clear()
        self.nbytes = 0
