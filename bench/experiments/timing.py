"""Replay timing and result files shared by the kernel experiments."""
from __future__ import annotations

import datetime
import json
import os

import torch


def pct(xs: list[float], q: float) -> float:
    """The ``q`` quantile of ``xs`` as the sample at index ``int(q * n)`` of the sorted values."""
    xs = sorted(xs)
    return xs[min(len(xs) - 1, int(q * len(xs)))]


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


def float_copy(out):
    """A float copy of a stage's output: a tensor, or the floating tensors of a dict (a VLM handoff)."""
    if isinstance(out, dict):
        return {k: v.float().clone() for k, v in out.items() if v.is_floating_point()}
    return out.float().clone()


def capture_checked(body, pool, warmup: int = 2) -> tuple:
    """``warmup`` eager calls of ``body``, then its CUDA graph captured into ``pool`` and replayed
    once: (graph, the last eager output, the graph's output), the outputs as float copies
    (``float_copy``: tensors, or dicts of them)."""
    for _ in range(warmup):
        eager = body()
    torch.cuda.synchronize()
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph, pool=pool):
        out = body()
    graph.replay()
    torch.cuda.synchronize()
    return graph, float_copy(eager), float_copy(out)


def seeded_inputs(model, batch: int, device: torch.device, half_prompt: bool = False) -> tuple:
    """The experiments' inputs at ``batch``: (images, state, tokens, bf16 noise), drawn in that order from a
    generator seeded with 1234 + batch; ``half_prompt`` pads the second half of each prompt (token 0)."""
    gen = torch.Generator().manual_seed(1234 + batch)
    images, state, tokens = model.example_inputs(batch, device=device, generator=gen)
    if half_prompt:
        tokens[:, model.io.prompt_len // 2:] = 0
    return images, state, tokens, model.noise(batch, device=device, generator=gen).to(torch.bfloat16)


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


def alternating_ms(graphs: dict, reps: int, warmup: int = 5) -> dict:
    """Per graph name, milliseconds of each of ``reps`` replays; the graphs are replayed in
    turn on the current stream, each replay synchronised, after ``warmup`` untimed rounds."""
    for _ in range(warmup):
        for graph in graphs.values():
            graph.replay()
    torch.cuda.synchronize()
    times = {name: [] for name in graphs}
    for _ in range(reps):
        for name, graph in graphs.items():
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            graph.replay()
            end.record()
            end.synchronize()
            times[name].append(start.elapsed_time(end))
    return times


def route_expert_layers(mode: dict, key: str, make_state, layer_fn) -> None:
    """Send ``DecoderLayer.forward_fused`` (the action stages' layer path) to ``layer_fn`` while
    ``mode[key]`` is true. One state per stage call, made by ``make_state(device)`` and kept on
    the call's workspace (also in ``mode["state"]``)."""
    from shared.models import layers
    original = layers.DecoderLayer.forward_fused

    def forward_fused(self, x, k_out, v_out, rope, bias, k_all, v_all, ws):
        if not mode[key]:
            return original(self, x, k_out, v_out, rope, bias, k_all, v_all, ws)
        state = getattr(ws, "_" + key, None)
        if state is None:
            state = mode["state"] = make_state(x.device)
            setattr(ws, "_" + key, state)
        return layer_fn(self, x, k_out, v_out, rope, bias, k_all, v_all, state)

    layers.DecoderLayer.forward_fused = forward_fused


def env_settings(models: str, batches: str, iters: int = 100) -> tuple[list[str], list[int], int]:
    """MODELS, BATCHES (comma-separated) and ITERS from the environment, with these defaults."""
    return (os.environ.get("MODELS", models).split(","), [int(b) for b in os.environ.get("BATCHES", batches).split(",")],
            int(os.environ.get("ITERS", str(iters))))


def result_header(iters: int) -> dict:
    """GPU, torch, commit (ROBION_COMMIT) and UTC time of a run, for its JSON file."""
    return {"gpu": torch.cuda.get_device_name(), "torch": torch.__version__, "commit": os.environ.get("ROBION_COMMIT"),
            "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"), "iters": iters}


def save_result(res: dict, stem: str) -> str:
    """Writes ``res`` to OUT (default /tmp) as OUT_NAME or ``<stem>_<gpu model>.json``; returns the path."""
    name = os.environ.get("OUT_NAME") or f"{stem}_{res['gpu'].split()[1].lower()}.json"
    path = os.path.join(os.environ.get("OUT", "/tmp"), name)
    with open(path, "w") as fh:
        json.dump(res, fh, indent=1)
    return path
