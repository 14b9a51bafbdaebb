"""A mergeable latency histogram: log-spaced bins, so agents can send it and the fleet can sum it."""

from __future__ import annotations

import math

BINS_PER_DECADE = 40
LO_MS = 1e-3  # bin 0 starts at 1 microsecond


class LatencyHistogram:
    def __init__(self) -> None:
        self.counts: dict[int, int] = {}

    @staticmethod
    def bin_of(ms: float) -> int:
        return max(0, int(math.floor(math.log10(max(ms, LO_MS) / LO_MS) * BINS_PER_DECADE)))

    @staticmethod
    def upper_ms(b: int) -> float:
        return LO_MS * 10 ** ((b + 1) / BINS_PER_DECADE)

    def add(self, ms: float) -> None:
        b = self.bin_of(ms)
        self.counts[b] = self.counts.get(b, 0) + 1

    def merge(self, other: dict[int, int]) -> None:
        for b, n in other.items():
            self.counts[int(b)] = self.counts.get(int(b), 0) + int(n)

    def as_dict(self) -> dict[int, int]:
        return dict(self.counts)

    @property
    def total(self) -> int:
        return sum(self.counts.values())

    def percentile(self, q: float) -> float | None:
        """The upper edge of the bin holding the q-th percentile (within 6 % of the true value)."""
        n = self.total
        if n == 0:
            return None
        rank = q / 100.0 * n
        acc = 0
        for b in sorted(self.counts):
            acc += self.counts[b]
            if acc >= rank:
                return self.upper_ms(b)
        return self.upper_ms(max(self.counts))
