"""Strobe sequences as plain data: which light fires on which 1/60 s tick, which cameras see it.

A :class:`Sequence` is a list of :class:`~mifacerf.capture.hardware.protocol.Step`
plus the tick period; it converts to and from JSON-able dicts so that tests can
diff sequences and a session's journal can record exactly what it asked for.

Light index ``l = arm_position * n_strobes + strobe`` (docs/conventions.md). The
paper's stage (30 strobes x 16 positions at 60 Hz) runs a full sequence in 8 s:
the arm turns continuously while the strobes flash in order, so arm positions
alternate direction (top -> bottom, then bottom -> top) to keep the flashes
evenly spaced along the arm's path (``serpentine=True``).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .protocol import MIN_PERIOD_US, Step


@dataclass
class Sequence:
    """Steps fired one per tick of ``period_us`` microseconds (>= 1/60 s)."""

    steps: list[Step] = field(default_factory=list)
    period_us: int = MIN_PERIOD_US
    n_strobes: int = 0

    def __post_init__(self):
        if self.period_us < MIN_PERIOD_US:
            raise ValueError(f"period {self.period_us} us is faster than the cameras' 60 Hz "
                             f"({MIN_PERIOD_US} us)")

    def __len__(self) -> int:
        return len(self.steps)

    @property
    def lights(self) -> np.ndarray:
        """Light index of every step, (n,) int."""
        return np.array([s.arm_position * self.n_strobes + s.strobe for s in self.steps], np.int64)

    @property
    def duration_s(self) -> float:
        return len(self.steps) * self.period_us * 1e-6

    def to_dict(self) -> dict:
        return {"period_us": self.period_us, "n_strobes": self.n_strobes,
                "steps": [[s.arm_position, s.strobe, s.camera_mask] for s in self.steps]}

    @classmethod
    def from_dict(cls, d: dict) -> "Sequence":
        return cls([Step(int(a), int(s), int(m)) for a, s, m in d["steps"]], int(d["period_us"]),
                   int(d["n_strobes"]))


def olat_sequence(n_positions: int, n_strobes: int, lights=None, *, camera_mask: int = 0xFF,
                  period_us: int = MIN_PERIOD_US, serpentine: bool = True) -> Sequence:
    """One-light-at-a-time sequence over ``lights`` (default: all), in firing order.

    Lights are grouped by arm position (ascending); within a position strobes run
    top -> bottom, or alternately bottom -> top with ``serpentine``.
    """
    if n_positions < 1 or n_strobes < 1:
        raise ValueError("a light stage needs at least one arm position and one strobe")
    n = n_positions * n_strobes
    idx = np.arange(n) if lights is None else np.unique(np.asarray(lights, np.int64).reshape(-1))
    if idx.size and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"light indices must lie in [0, {n}), got {idx.min()}..{idx.max()}")
    steps = []
    for pos in np.unique(idx // n_strobes):
        strobes = np.sort(idx[idx // n_strobes == pos] % n_strobes)
        if serpentine and pos % 2 == 1:
            strobes = strobes[::-1]
        steps += [Step(int(pos), int(k), camera_mask) for k in strobes]
    return Sequence(steps, period_us, n_strobes)
