"""Ablations of the robion engine: the same lockstep loop, graphs, buffers and queues, with
the SM restriction varied.

- ``disagg``: stage disaggregation only (two streams, locksteps, no SM restriction);
- ``static``: the VLM stream always restricted to ``static_sms`` SMs (default: half the
  device's SMs rounded to a multiple of 8, 64 on an H100);
- ``disjoint``: two non-overlapping green contexts, the VLM stage on N SMs and the action
  stage on the rest; VLM graphs are captured on the VLM partition and action graphs on the
  action partition (a graph keeps the SM limit of the stream it was captured on), each with
  its GEMMs planned for its partition's SMs (``graphs.gemm_sm_target``). N is
  ``disjoint_sms`` or, when that is 0, profiled (``profile_disjoint``) and cached.

On the CPU all three run the lockstep loop with ``HostRunner`` (no SMs to restrict).
"""

from __future__ import annotations

import json
import logging
import statistics
import time
from pathlib import Path

import torch

from services.executor.lockstep import CudaRunner, LockstepEngine, batch_sizes
from services.executor.profiler import GEMM_PLAN, time_lockstep
from services.executor.sm import SM_GRANULARITY, StaticLevel, Unrestricted, sm_count, split_disjoint

log = logging.getLogger(__name__)


def half_sms(total: int) -> int:
    """Half the SMs, rounded to the nearest multiple of the green-context granularity (132 -> 64)."""
    return max(SM_GRANULARITY, int(round(total / 2 / SM_GRANULARITY)) * SM_GRANULARITY)


class DisaggEngine(LockstepEngine):
    """``engine.kind: disagg``: two streams in locksteps, VLM unrestricted."""

    def __init__(self, models, cfg, device, on_results):
        super().__init__(models, cfg, device, on_results, sm_policy=Unrestricted())


class StaticEngine(LockstepEngine):
    """``engine.kind: static``: the VLM stream restricted to a fixed SM count at every lockstep."""

    def __init__(self, models, cfg, device, on_results):
        super().__init__(models, cfg, device, on_results, sm_policy=Unrestricted())
        self.static_sms: int | None = None

    def _prepare_cuda(self) -> None:
        total = sm_count(self.device)
        self.static_sms = self.cfg.static_sms or half_sms(total)
        if not 0 < self.static_sms < total:
            raise ValueError(f"engine.static_sms: {self.static_sms} is not below the device's {total} SMs")
        self.sm_policy = StaticLevel(self.static_sms)
        super()._prepare_cuda()


class DisjointEngine(LockstepEngine):
    """``engine.kind: disjoint``: VLM and action stages on two disjoint SM partitions."""

    def __init__(self, models, cfg, device, on_results):
        self.partition = None
        self.disjoint_profile: dict | None = None
        super().__init__(models, cfg, device, on_results, sm_policy=Unrestricted())

    # The lockstep engine builds its CudaRunner (and captures every graph on the runner's two
    # streams) inside _prepare_cuda; swapping the runner's streams for the partition's as it is
    # assigned puts every capture, upload, handoff and replay on the partition. (A public
    # "streams" hook in LockstepEngine would make this explicit.)
    @property
    def runner(self):
        return self._runner

    @runner.setter
    def runner(self, r) -> None:
        if isinstance(r, CudaRunner) and self.partition is not None:
            r.vlm_stream, r.action_stream = self.partition.vlm_stream, self.partition.action_stream
        self._runner = r

    def _stream_sms(self) -> tuple[int | None, int | None]:
        return self.partition.vlm_sms, self.partition.action_sms

    def _prepare_cuda(self) -> None:
        torch.cuda.set_device(self.device)
        n = self.cfg.disjoint_sms
        if not n:
            self.disjoint_profile = profile_disjoint(self.models, self.device, self.cfg)
            n = self.disjoint_profile["best_sms"]
        self.partition = split_disjoint(self.device, n)
        log.info("disjoint partition: VLM %d SMs, action %d SMs", self.partition.vlm_sms, self.partition.action_sms)
        super()._prepare_cuda()


def _candidates(total: int) -> list[int]:
    return list(range(SM_GRANULARITY, total - SM_GRANULARITY + 1, SM_GRANULARITY))


def _profile_path(cfg, gpu: str, archs: list[str]) -> Path:
    from services.executor.profiler import table_path

    p = table_path(cfg.profile_dir, gpu, torch.__version__, cfg.max_batch, archs)
    return p.with_name(p.name.replace("sm-table_", "disjoint_", 1))


def _time_partition(part, stages: dict, runner, combos: list, sizes: list[int],
                    repeats: int) -> tuple[float, dict[str, float]]:
    """Capture every architecture's graphs on ``part`` and time each combination as one lockstep."""
    runner.vlm_stream, runner.action_stream = part.vlm_stream, part.action_stream
    for st in stages.values():
        st.vlm_graphs.clear()
        st.action_graphs.clear()
        st.capture_stream, st.action_stream = part.vlm_stream, part.action_stream
        st.stream_sms = (part.vlm_sms, part.action_sms)
        st.capture_action()
        for b in sizes:
            st.capture_vlm(b, {None})
    per = {f"{va}x{vb}|{aa}x{ab}": time_lockstep(runner, stages[va], vb, stages[aa], ab, None, repeats)
           for va, vb, aa, ab in combos}
    return statistics.mean(per.values()), per


def profile_disjoint(models: dict, device: torch.device, cfg, repeats: int | None = None) -> dict:
    """Pick the VLM partition size N (multiples of 8) that minimises the mean lockstep time.

    For every candidate N the device is split once into N and the rest; each served
    architecture's VLM graphs are captured on the N partition and its action graphs on the
    rest, and every (VLM batch, action batch) combination of that architecture (and across
    architectures when several are co-located) is timed as one lockstep with the engine's
    own runner (median of ``repeats`` after 2 warm-ups). The objective is the mean over the
    combinations: one partition serves all of them, unlike the table's per-combination
    level. The result is cached in ``profile_dir`` (``disjoint_<gpu>_torch<v>_mb<b>_<archs>.json``).
    """
    from services.executor.graphs import GraphPools, GraphStages
    from services.executor.stages import profile_key

    repeats = repeats or cfg.profile_repeats
    gpu = torch.cuda.get_device_name(device)
    by_arch = {}
    for m in models.values():
        by_arch.setdefault(profile_key(m.model), m.model)
    archs = sorted(by_arch)
    path = _profile_path(cfg, gpu, archs)
    if path.exists():
        doc = json.loads(path.read_text())
        # Profiles from before the partitions' GEMMs were planned for their SMs time other graphs.
        if doc.get("archs") == archs and doc.get("max_batch") == cfg.max_batch and doc.get("gemm_plan") == GEMM_PLAN:
            log.info("disjoint partition from %s: %s SMs", path, doc["best_sms"])
            return doc
    t0 = time.perf_counter()
    sizes = batch_sizes(cfg.max_batch)
    combos = [(va, vb, aa, ab) for va in archs for vb in sizes for aa in archs for ab in sizes]
    total = sm_count(device)
    runner = CudaRunner(device)
    pools = GraphPools.create()
    stages = {a: GraphStages(m, device, sizes, cfg.seed, pools, None, runner.vlm_stream, runner.action_stream)
              for a, m in by_arch.items()}
    for st in stages.values():
        st.allocate()
    times: dict[str, float] = {}
    per_combo: dict[str, dict[str, float]] = {}
    failed: dict[str, str] = {}
    for n in _candidates(total):
        part = split_disjoint(device, n)
        try:
            times[str(n)], per_combo[str(n)] = _time_partition(part, stages, runner, combos, sizes, repeats)
            log.info("disjoint %d/%d SMs: mean lockstep %.3f ms", n, total - n, times[str(n)])
        except RuntimeError as exc:
            # A library kernel may not run on a partition this small (its launch needs more
            # SMs than the partition has): that split is not a candidate, the others still are.
            failed[str(n)] = str(exc).splitlines()[0][:300]
            log.warning("disjoint %d/%d SMs cannot run the stages, skipped: %s", n, total - n, failed[str(n)])
        finally:
            torch.cuda.synchronize(device)
            for st in stages.values():
                st.vlm_graphs.clear()
                st.action_graphs.clear()
            del part
    if not times:
        raise RuntimeError(f"disjoint: no VLM partition size could run the stages ({failed})")
    best = min(times, key=times.get)
    doc = {"gpu": gpu, "sm_count": total, "torch": torch.__version__, "max_batch": cfg.max_batch, "archs": archs,
           "objective": "mean lockstep time over the (vlm, action) batch combinations", "repeats": repeats,
           "gemm_plan": GEMM_PLAN, "best_sms": int(best), "mean_ms": times, "combo_ms": per_combo, "failed": failed,
           "profile_s": time.perf_counter() - t0}
    del stages
    torch.cuda.synchronize(device)
    torch.cuda.empty_cache()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(doc, indent=1) + "\n")
    except OSError:
        log.warning("could not cache the disjoint profile at %s", path)
    log.info("disjoint partition profiled in %.1f s: VLM %d SMs", doc["profile_s"], doc["best_sms"])
    return doc
