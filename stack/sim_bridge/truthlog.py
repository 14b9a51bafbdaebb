"""The world's ground truth per step (``truth.npz``), in bounded memory over a run of any length.

Each step appends one row per key (``rows[key].append``); every ``chunk`` whole steps the rows go to a spill
file beside the run's output (``.truth-<n>.npz``, uncompressed), so a one-hour 16-robot real-time run holds at
most one chunk in memory (the soak measured 75 MB/h of growth in the world when every row stayed in memory).
:meth:`save` writes ``truth.npz`` from the spilled chunks and the rest, and removes the spill files.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

KEYS = ("t", "x", "y", "yaw", "v", "w", "alive", "cmd_v", "cmd_w")
CHUNK = 600
"""Steps held in memory before they go to a spill file (1 min at dt 0.1 s; about 1.2 MB at 16 robots)."""


class TruthRows:
    def __init__(self, spill_dir: Path | None, chunk: int = CHUNK, extra: tuple[str, ...] = ()):
        self.keys = KEYS + extra  # extra: ``wall`` in real time (UNIX s of each row: two worlds' truths side by side)
        self.rows: dict[str, list] = {k: [] for k in self.keys}
        self.spill_dir, self.chunk = spill_dir, chunk
        self.spilled: list[Path] = []

    def __getitem__(self, key: str) -> list:
        return self.rows[key]

    def step_done(self) -> None:
        """After a whole step (every key has its row): spill the rows once a chunk is full."""
        if self.spill_dir is None or len(self.rows["t"]) < self.chunk:
            return
        self.spill_dir.mkdir(parents=True, exist_ok=True)
        path = self.spill_dir / f".truth-{len(self.spilled)}.npz"
        np.savez(path, **{k: np.array(v) for k, v in self.rows.items()})
        self.spilled.append(path)
        self.rows = {k: [] for k in self.keys}

    def arrays(self) -> dict[str, np.ndarray]:
        """Every row so far, spilled and held, one array per key."""
        parts: dict[str, list] = {k: [] for k in self.keys}
        for path in self.spilled:
            with np.load(path) as z:
                for k in self.keys:
                    parts[k].append(z[k])
        for k, v in self.rows.items():
            if v:
                parts[k].append(np.array(v))
        return {k: np.concatenate(p) if p else np.array([]) for k, p in parts.items()}

    def save(self, path: Path, **extra) -> None:
        np.savez_compressed(path, **extra, **self.arrays())
        for p in self.spilled:
            p.unlink(missing_ok=True)
        self.spilled = []
