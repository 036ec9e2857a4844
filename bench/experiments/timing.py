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


def replay_pair_ms(first: torch.cuda.CUDAGraph, second: torch.cuda.CUDAGraph, reps: int,
                   warmup: int = 5) -> tuple[list[float], list[float], list[float]]:
    """``reps`` back-to-back replays of two graphs on the current stream (a VLM graph, then the
    action graph reading its handoff), after ``warmup`` untimed pairs: each pair's ms of the
    first graph, of the second, and of both."""
    for _ in range(warmup):
        first.replay()
        second.replay()
    ev = [[torch.cuda.Event(enable_timing=True) for _ in range(3)] for _ in range(reps)]
    torch.cuda.synchronize()
    for e0, e1, e2 in ev:
        e0.record()
        first.replay()
        e1.record()
        second.replay()
        e2.record()
    torch.cuda.synchronize()
    return ([a.elapsed_time(b) for a, b, _ in ev], [b.elapsed_time(c) for _, b, c in ev],
            [a.elapsed_time(c) for a, _, c in ev])
