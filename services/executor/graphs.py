"""CUDA graphs of a model's stages: one per (batch size, SM level) for the VLM stage and one
per batch size for the action stage, over ``BufferedStages``' static buffers.

Why one VLM graph per SM level: a captured kernel keeps the execution context (and so the
SM limit) of the stream it was captured on, whatever stream replays it. Restricting the
VLM stage to a level therefore means capturing it on that level's green-context stream.

Why restricted VLM graphs are captured through cuBLASLt with an SM-count target: cuBLAS
picks a GEMM's kernel for the whole GPU, and a tile grid sized for one wave on 132 SMs takes
two waves on 128. On an H100, pi0's VLM at batch 2 took 12.8 ms on a 128-SM green context
against 10.9 ms on all 132 SMs, and one GEMM kernel went from 1.7 to 3.1 ms. cuBLASLt's
matmul descriptor carries the SM count to plan for (torch sets it from its SM carveout), and
a graph keeps the kernels chosen at capture: captured that way, the same VLM took 10.9 ms on
128 SMs and 12.4 instead of 14.8 on 96 (docs/RESULTS.md, "cuBLAS told the SM level"). Graphs
captured on a partition of their own (``stream_sms``, the disjoint engine) are planned for it
the same way, and so is an action graph when the SM table found it faster planned for the SMs
its usual lockstep leaves free (``action_plans``), or confined to those SMs
(``action_confine``); ``profiler.plan_actions`` chooses.

Memory: all VLM graphs share one pool and all action graphs another (pools are passed in,
so co-located models share them too). Graphs of one pool never run concurrently (one VLM
stream, one action stream), and every tensor a graph hands on lives in buffers allocated
outside the pools, so a later replay of another graph can only overwrite dead intermediates.
"""

from __future__ import annotations

import contextlib
import logging
import time
import warnings
from dataclasses import dataclass

import torch

from services.executor.sm import GreenStreams, Level, level_name
from services.executor.stages import BufferedStages
from shared.models.base import VLAModel

log = logging.getLogger(__name__)

WARMUP_RUNS = 2  # eager runs on the capture stream first: cuBLAS workspaces, lazy inits, autotuning


@contextlib.contextmanager
def gemm_sm_target(sms: int | None, device: torch.device):
    """GEMMs issued inside go through cuBLASLt planned for ``sms`` SMs (nothing changes for
    ``None`` or the whole GPU).

    Both settings are process-wide in torch (every thread and device), so this is for graph
    capture at start-up, while no other thread issues GEMMs; they are restored on exit."""
    total = torch.cuda.get_device_properties(device).multi_processor_count if sms is not None else 0
    if sms is None or sms >= total or not hasattr(torch._C, "_set_sm_carveout_experimental"):
        yield
        return
    blas = torch.backends.cuda.preferred_blas_library()
    carveout = torch._C._get_sm_carveout_experimental()
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message=".*SM carveout.*")  # torch calls the knob experimental
            torch._C._set_sm_carveout_experimental(total - sms)
        torch.backends.cuda.preferred_blas_library("cublaslt")
        yield
    finally:
        torch._C._set_sm_carveout_experimental(carveout)
        torch.backends.cuda.preferred_blas_library(blas)


@dataclass
class GraphPools:
    """Memory pools shared by every model's graphs on one device."""

    vlm: tuple
    action: tuple

    @classmethod
    def create(cls) -> "GraphPools":
        return cls(torch.cuda.graph_pool_handle(), torch.cuda.graph_pool_handle())


class GraphStages(BufferedStages):
    """``BufferedStages`` whose VLM and action steps replay captured CUDA graphs."""

    def __init__(self, model: VLAModel, device: torch.device, batch_sizes: list[int], seed: int,
                 pools: GraphPools, green: GreenStreams | None, capture_stream: torch.cuda.Stream,
                 action_stream: torch.cuda.Stream | None = None,
                 stream_sms: tuple[int | None, int | None] = (None, None)):
        super().__init__(model, device, batch_sizes, seed)
        self.pools = pools
        self.green = green
        self.capture_stream = capture_stream  # unrestricted VLM captures (level None)
        self.action_stream = action_stream or capture_stream
        # SMs of capture_stream and action_stream when they are partitions of their own (the
        # disjoint engine); None: the whole GPU. Graphs captured there plan their GEMMs for it.
        self.stream_sms = stream_sms
        # Batch -> SMs its action graph plans its GEMMs for, when the SM table chose one
        # (``profiler.plan_actions``); otherwise the action stream's (``stream_sms[1]``).
        self.action_plans: dict[int, int | None] = {}
        # Batch -> VLM level whose free SMs (``GreenStreams.complement``) its action graph is
        # confined to, when the SM table chose that; otherwise the action stream's SMs.
        self.action_confine: dict[int, int | None] = {}
        self.vlm_graphs: dict[tuple[int, Level], torch.cuda.CUDAGraph] = {}
        self.action_graphs: dict[int, torch.cuda.CUDAGraph] = {}
        self.capture_s = 0.0

    def _stream(self, level: Level) -> torch.cuda.Stream:
        if level is None:
            return self.capture_stream
        if self.green is None:
            raise RuntimeError(f"SM level {level} needs green contexts, which this engine did not create")
        return self.green.stream(level)

    def _capture(self, body, stream: torch.cuda.Stream, pool: tuple) -> torch.cuda.CUDAGraph:
        stream.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(stream):
            for _ in range(WARMUP_RUNS):
                body()
        stream.synchronize()
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph, pool=pool, stream=stream):
            body()
        stream.synchronize()
        return graph

    def capture_action(self) -> None:
        t0 = time.perf_counter()
        for b in self.batch_sizes:
            if b not in self.action_graphs:
                stream, plan = self.action_stream, self.action_plans.get(b) or self.stream_sms[1]
                confine = self.action_confine.get(b)
                if confine is not None:
                    if self.green is None:
                        raise RuntimeError("confining the action stage needs green contexts, which this engine did "
                                           "not create")
                    stream, plan = self.green.complement(confine)
                with gemm_sm_target(plan, self.device):
                    self.action_graphs[b] = self._capture(lambda b=b: self._action_body(b), stream,
                                                          self.pools.action)
        self.capture_s += time.perf_counter() - t0

    def replan_action(self, b: int, sms: int | None, confine: int | None = None) -> None:
        """Capture batch ``b``'s action graph again: its GEMMs planned for ``sms`` SMs (None: the
        action stream's own) or, with ``confine``, on the SMs a VLM at that level leaves free."""
        self.set_action_plans({b: (sms, confine)})

    def set_action_plans(self, plans: dict[int, tuple[int | None, int | None]]) -> None:
        """Batch -> (SMs, confine) as an SM table chose them (see ``replan_action``). Only graphs
        whose plan changed, or that are missing, are captured, each once."""
        for b, (sms, confine) in plans.items():
            if confine is not None:
                sms = None  # planned for the complement's own SM count
            if (self.action_plans.get(b), self.action_confine.get(b)) != (sms, confine):
                self.action_graphs.pop(b, None)
            self.action_plans[b], self.action_confine[b] = sms, confine
        self.capture_action()

    def capture_vlm(self, b: int, levels: set[Level]) -> None:
        t0 = time.perf_counter()
        for level in sorted(levels, key=lambda lv: (lv is None, lv or 0)):
            if (b, level) not in self.vlm_graphs:
                stream = self._stream(level)
                with gemm_sm_target(self.stream_sms[0] if level is None else level, self.device):
                    self.vlm_graphs[(b, level)] = self._capture(lambda: self._vlm_body(b), stream, self.pools.vlm)
        dt = time.perf_counter() - t0
        self.capture_s += dt
        log.debug("%s: VLM graphs for batch %d at levels %s in %.2f s", self.arch, b,
                  [level_name(lv) for lv in levels], dt)

    def drop_vlm(self, keep: dict[int, set[Level]]) -> None:
        """Release VLM graphs of levels the serving table does not use (after profiling)."""
        for key in [k for k in self.vlm_graphs if k[1] not in keep.get(k[0], set())]:
            del self.vlm_graphs[key]

    def vlm(self, b: int, level: Level = None) -> None:
        self.upload(b)
        graph = self.vlm_graphs.get((b, level))
        if graph is None:
            raise KeyError(f"{self.arch}: no VLM graph for batch {b} at SM level {level_name(level)}")
        graph.replay()

    def action(self, b: int, slot: int) -> None:
        self.action_graphs[b].replay()
        self.host_out[b][slot].copy_(self.dev_out[b], non_blocking=True)
