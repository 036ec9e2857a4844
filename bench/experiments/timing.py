"""Replay timing shared by the kernel experiments."""
from __future__ import annotations

import torch


def replay_ms(graph: torch.cuda.CUDAGraph, stream: torch.cuda.Stream, reps: int, warmup: int = 5) -> list[float]:
    """Milliseconds of each of ``reps`` replays of ``graph`` on ``stream``, after ``warmup``
    untimed ones; each replay is synchronised, so none overlaps the next."""
    times = []
    for i in range(reps + warmup):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record(stream)
        with torch.cuda.stream(stream):
            graph.replay()
        end.record(stream)
        end.synchronize()
        if i >= warmup:
            times.append(start.elapsed_time(end))
    return times
