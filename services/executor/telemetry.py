"""Per-lockstep telemetry: what ran, at which SM level, how long, and the gap before it.

Records are finalised one lockstep late (when their CUDA events are certainly complete and
the next lockstep is already running), so keeping telemetry costs the GPU nothing.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

log = logging.getLogger(__name__)


@dataclass
class LockstepRecord:
    index: int
    start: float  # time.monotonic() when the lockstep was launched
    vlm_model: str | None
    vlm_arch: str | None
    vlm_batch: int
    action_model: str | None
    action_arch: str | None
    action_batch: int
    sm_level: int | None  # SMs of the VLM stream; None: unrestricted
    duration_ms: float  # first stage start to last stage end (device time on the GPU)
    vlm_ms: float
    action_ms: float
    # Host time on the critical path between the previous lockstep and this one: from observing
    # the previous lockstep's end to having issued this one, or 0 when this one was issued ahead
    # (enqueued behind the previous one's end events before that end). A launch-ahead that the
    # previous lockstep's end overtook counts its whole launch time (an upper bound). None when
    # the engine idled in between (no back-to-back locksteps).
    cpu_gap_us: float | None = None
    # Device idle time between the previous lockstep's last kernel and this one's first
    # (CUDA events; includes the host's wake-up latency). None on the CPU or after idling.
    gpu_gap_us: float | None = None
    # Same, up to the later of the two stages' first kernel (what the second-launched stage loses).
    gpu_gap_last_us: float | None = None
    # Host time to decide (scheduler pick, SM level) and issue this lockstep, on or off the critical path.
    launch_us: float | None = None
    # Issued ahead: enqueued while the previous lockstep still ran, gated on its end events.
    ahead: bool = False
    # For locksteps issued ahead: how long before the previous lockstep's end (as the host saw
    # it) everything was issued, and how long before that end the batch was admitted (the
    # admission point's shift that launch-ahead costs).
    lead_us: float | None = None
    admit_early_us: float | None = None
    # The launch-ahead slack in force when it was decided, and how late the engine woke for it.
    slack_us: float | None = None
    wake_late_us: float | None = None

    @property
    def overlap_ms(self) -> float:
        """How much the two stages ran at the same time (0 when one was absent or they serialised)."""
        if not (self.vlm_batch and self.action_batch):
            return 0.0
        return max(0.0, self.vlm_ms + self.action_ms - self.duration_ms)


class Telemetry:
    """A ring buffer of the latest lockstep records, optionally mirrored to a JSONL file.

    The file is best-effort: it must never cost a request its reply nor stop the engine, so
    a file that cannot be opened or written (disk full, file closed under us) is logged once
    and dropped, and the ring buffer (what the metrics read) carries on.
    """

    def __init__(self, capacity: int = 4096, path: str | Path | None = None):
        self._ring: deque[LockstepRecord] = deque(maxlen=capacity)
        self._lock = threading.Lock()
        self._file: IO[str] | None = None
        self._path: Path | None = None
        self.file_failed = False  # the file was dropped after an error
        self.count = 0
        if path:
            self.open(path)

    def open(self, path: str | Path) -> None:
        path = self._path = Path(path)
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = path.open("a", buffering=1)
        except OSError as exc:
            self._drop_file(exc)

    def add(self, rec: LockstepRecord) -> None:
        with self._lock:
            self._ring.append(rec)
            self.count += 1
        if self._file is not None:
            try:
                self._file.write(json.dumps(dataclasses.asdict(rec)) + "\n")
            except (OSError, ValueError) as exc:  # ValueError: the file was closed
                self._drop_file(exc)

    def _drop_file(self, exc: Exception) -> None:
        """Stop mirroring to the file: one warning, then the ring buffer alone."""
        f, self._file = self._file, None
        if not self.file_failed:
            log.warning("telemetry file %s failed (%s); no longer writing it (serving carries on)", self._path, exc)
        self.file_failed = True
        if f is not None:
            try:
                f.close()  # flushes what is buffered: may fail again for the same reason
            except (OSError, ValueError):
                pass

    def records(self) -> list[LockstepRecord]:
        with self._lock:
            return list(self._ring)

    def clear(self) -> None:
        with self._lock:
            self._ring.clear()

    def close(self) -> None:
        """Close the file; never raises (it runs in the engine's shutdown, after the last replies)."""
        f, self._file = self._file, None
        if f is not None:
            try:
                f.close()
            except (OSError, ValueError) as exc:
                log.warning("closing telemetry file %s failed: %s", self._path, exc)

    def summary(self) -> dict:
        return summarize(self.records())


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def _stats(values: list[float]) -> dict:
    return {"n": len(values), "median": _pct(values, 50), "p99": _pct(values, 99)}


def summarize(records: list[LockstepRecord]) -> dict:
    """Gap percentiles over back-to-back locksteps and how often the stages overlapped."""
    cpu = [r.cpu_gap_us for r in records if r.cpu_gap_us is not None]
    b2b = [r for r in records if r.cpu_gap_us is not None]
    gpu = [r.gpu_gap_us for r in records if r.gpu_gap_us is not None]
    gpu_last = [r.gpu_gap_last_us for r in records if r.gpu_gap_last_us is not None]
    both = [r for r in records if r.vlm_batch and r.action_batch]
    return {
        "locksteps": len(records),
        "co_running": len(both),
        "overlapping": sum(r.overlap_ms > 0 for r in both),
        "mean_overlap_ms": float(np.mean([r.overlap_ms for r in both])) if both else None,
        "mean_duration_ms": float(np.mean([r.duration_ms for r in records])) if records else None,
        "cpu_gap_us": {"n": len(cpu), "median": _pct(cpu, 50), "p99": _pct(cpu, 99)},
        "gpu_gap_us": {"n": len(gpu), "median": _pct(gpu, 50), "p99": _pct(gpu, 99)},
        "gpu_gap_last_us": {"n": len(gpu_last), "median": _pct(gpu_last, 50), "p99": _pct(gpu_last, 99)},
        "launch_us": _stats([r.launch_us for r in records if r.launch_us is not None]),
        "ahead": sum(r.ahead for r in b2b),
        "back_to_back": len(b2b),
        "lead_us": _stats([r.lead_us for r in records if r.lead_us is not None]),
        "admit_early_us": _stats([r.admit_early_us for r in records if r.admit_early_us is not None]),
        "slack_us": _stats([r.slack_us for r in records if r.slack_us is not None]),
        "wake_late_us": _stats([r.wake_late_us for r in records if r.wake_late_us is not None]),
        "sm_levels": sorted({str(r.sm_level) for r in records if r.vlm_batch}),
    }
