"""Robot limits C_i: how many robots of a model one GPU sustains at the target SLO attainment.

Found by driving simulated robots through this executor's own engine (the capacity search
of services/executor/simulation.py) before the executor starts serving, and cached by GPU
name, architecture, frequency, max_batch, deadline and engine, so a restart or another
executor on the same kind of GPU reuses them. Each executor measures only the models it
owns (the first executor in the config hosting the model), so executors on separate GPUs
measure in parallel and nothing is measured twice.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import threading
import time
from collections.abc import Mapping
from pathlib import Path

import torch

from services.executor.engine import ServedModel, make_engine, resolve_kind
from services.executor.simulation import SearchCancelled, SimConfig, find_capacity, meets
from shared.config import ClusterConfig, EngineConfig, LimitsConfig, ModelConfig
from shared.files import exclusive, write_atomic

log = logging.getLogger("robion.executor")


def device_name(device: torch.device) -> str:
    return torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"


# Engine settings besides kind and max_batch that change how many robots one GPU serves. A key names those set away
# from their defaults (and a network other than the default), so the usual config keeps the keys it always had.
LIMIT_ENGINE_FIELDS = ("policy", "shed_late", "sm_policy", "static_sms", "disjoint_sms", "graphs", "running_batch",
                       "handoff_slots", "procdisagg_workers", "vlm_devices", "action_devices")
DEFAULT_NETWORK = LimitsConfig.network


def limit_key(gpu: str, arch: str, size: str, hz: float, max_batch: int, slo_ms: float, kind: str, target: float,
              network: str = DEFAULT_NETWORK, engine: EngineConfig | None = None) -> str:
    """What a limit depends on; fine-tuned variants of one architecture share it (also the
    key of the traffic bench's limit files, so either can read the other's). Without the network and the engine's
    other settings, a limit measured over one network or engine was reused for another."""
    parts = [gpu, f"{arch}:{size}", f"{hz:g}Hz", f"mb{max_batch}", f"{slo_ms:g}ms", kind, f"at{target:g}"]
    if network != DEFAULT_NETWORK:
        parts.append(f"net:{network}")
    if engine is not None:
        default = EngineConfig()
        parts += [f"{f}={getattr(engine, f)}" for f in LIMIT_ENGINE_FIELDS if getattr(engine, f) != getattr(default, f)]
    return "|".join(parts)


class LimitCache:
    """A JSON file of measured limits, shared by the executors of one state directory."""

    def __init__(self, path: str | Path):
        self.path = Path(path)

    def read(self) -> dict[str, dict]:
        try:
            data = json.loads(self.path.read_text())
        except (OSError, ValueError):
            return {}
        if not isinstance(data, dict):  # hand-edited into another shape: nothing in it is usable
            log.warning("%s is not a JSON object; measuring as if it were empty", self.path)
            return {}
        return data

    def write(self, key: str, entry: dict) -> bool:
        """Add one entry; False (and a warning) when the file cannot be written: the limit still holds for this
        process, and a state directory that is read-only or full must not end it after a search of minutes.

        Executors on other GPUs write the same file: the read-modify-replace runs under an exclusive lock on a
        file beside it, or two overlapping writes would each drop the other's new entries."""
        try:
            with exclusive(self.path):
                data = self.read()
                data[key] = entry
                write_atomic(self.path, json.dumps(data, indent=2, sort_keys=True))
        except OSError as exc:
            log.warning("could not write the robot limit cache %s (%s): the limit holds until this process ends",
                        self.path, exc.strerror or exc)
            return False
        return True


def cached_limit(entry: object) -> int | None:
    """The limit a cache entry holds, or None when it is not a positive integer.

    The file may be edited by hand (docs/operations.md): 0, negative, fractional, inf and NaN
    (Python's JSON reads Infinity and NaN), strings and booleans are no limit at all.
    """
    limit = entry.get("limit") if isinstance(entry, dict) else None
    if isinstance(limit, bool) or not isinstance(limit, (int, float)):
        return None
    if isinstance(limit, float) and not limit.is_integer():  # also inf and NaN
        return None
    return int(limit) if limit > 0 else None


def _failed_at(entry: dict, limit: int, target: float) -> bool:
    """Whether the cached search's own points show ``limit`` robots below ``target`` (entries without points pass)."""
    points = entry.get("points") if isinstance(entry, dict) else None
    if not isinstance(points, list):
        return False
    return any(isinstance(p, dict) and p.get("robots") == limit and isinstance(p.get("slo_attainment"), (int, float))
               and not meets(p["slo_attainment"], target) for p in points)


def owned_models(cfg: ClusterConfig, executor: str, hosted: list[str]) -> list[str]:
    """Models this executor measures: those it is the first executor in the config to host."""
    first: dict[str, str] = {}
    for ex in cfg.executors:
        for m in ex.models:
            first.setdefault(m, ex.name)
    return [m for m in hosted if first.get(m, executor) == executor]


def measure_limits(cfg: ClusterConfig, executor: str, models: dict[str, ServedModel], device: torch.device, *,
                   settings: Mapping[str, ModelConfig] | None = None, measure: bool = True,
                   stop: threading.Event | None = None) -> dict[str, int]:
    """Limits for the models this executor owns and the config leaves open; cached ones are reused.

    ``settings``: each model's settings (default the config's; a reload passes the ones it loaded, whose rate or
    deadline may differ). ``measure`` False: cached limits only. ``stop`` set: the search ends between epochs and
    the model being measured gets no limit (nothing is cached for it); the ones found so far are returned.
    """
    lc = cfg.control.limits
    cache = LimitCache(Path(cfg.control.state_dir) / "limits.json")
    known = cache.read()
    out: dict[str, int] = {}
    # Measured only by a model's first host in the config, so two executors never search for the same limit. A
    # cached one is reported by every host: a reload after an apply moved a model to an executor that was not its
    # first host in this process's file would otherwise report it nowhere (nor would a start while that host is down).
    owned = set(owned_models(cfg, executor, list(models))) if measure else set()
    for name in models:
        mc = settings[name] if settings is not None and name in settings else cfg.model(name)
        if mc.limit is not None:
            continue
        served = models[name]
        key = limit_key(device_name(device), served.model.arch, mc.size, mc.hz, cfg.engine.max_batch, served.slo_s * 1e3,
                        resolve_kind(cfg.engine.kind, device), lc.target, lc.network, cfg.engine)
        if key in known:
            limit = cached_limit(known[key])
            cap = known[key].get("max_robots") if isinstance(known[key], dict) else None
            if limit is not None and _failed_at(known[key], limit, lc.target):
                # Written before a search that found no count meeting the target cached nothing: it cached 1.
                log.warning("%s: the cached limit %d of %s missed the target at that count; measuring it again",
                            cache.path, limit, key)
            elif limit is not None and name in owned and isinstance(cap, int) and limit >= cap and cap < lc.max_robots:
                # The search stopped at its cap, not at the GPU's limit: a higher cap may find more.
                log.info("%s: the cached limit %d of %s was the search's cap; measuring again up to %d",
                         cache.path, limit, key, lc.max_robots)
                limit = None
            elif limit is not None:
                out[name] = limit
                continue
            else:
                # Reporting it would crash this executor (int(NaN)) or mislead the solver (int(2.5)).
                log.warning("%s: %s has limit %r, not a positive integer; measuring it again",
                            cache.path, key, known[key].get("limit") if isinstance(known[key], dict) else known[key])
        if name not in owned:
            if not measure:
                log.warning("no cached robot limit for %s at its settings (%s): it is planned without one until it "
                            "is measured (at the executor's next start) or given in models[].limit", name, key)
            continue
        log.info("measuring the robot limit of %s (%s) at %g Hz ...", name, key, mc.hz)
        t0 = time.monotonic()
        # The simulated robots' locksteps are no serving telemetry: kept out of the engine's telemetry file.
        engine_cfg = dataclasses.replace(cfg.engine, telemetry_file=None)
        try:
            result = find_capacity(lambda sink: make_engine({name: served}, engine_cfg, device, sink), name,
                                   # At least one period: a model called less often than once per duration_s
                                   # would send nothing in an epoch (the harness refuses that).
                                   hz=mc.hz, sim=SimConfig(epochs=lc.epochs, duration_s=max(lc.duration_s, 1 / mc.hz),
                                                           seed=lc.seed, network=lc.network),
                                   target=lc.target, max_robots=lc.max_robots, progress=lc.progress, cancel=stop)
        except SearchCancelled:
            log.info("stopped while measuring the robot limit of %s", name)
            return out
        took = time.monotonic() - t0
        if result.capacity < 1:
            # A limit of 1 here (as before) promised a robot the model cannot serve, and was cached, so no later
            # start measured again. No count met the target: no limit, nothing cached, measured at the next start.
            log.warning("robot limit of %s: not even 1 robot meets %.0f%% of its %g ms deadline at %g Hz (search took "
                        "%.0f s); it is planned without a limit until measured again at the next start or given in "
                        "models[].limit. Is its slo_ms too tight for this GPU?",
                        name, 100 * lc.target, served.slo_s * 1e3, mc.hz, took)
            continue
        limit = result.capacity
        entry = {"limit": limit, "max_robots": lc.max_robots, "measured_s": round(took, 1), "points": [
            {"robots": p.robots, "slo_attainment": p.slo_attainment} for p in result.points]}
        cache.write(key, entry)
        known[key] = entry  # a fine-tuned variant of the same architecture and settings reuses it
        log.info("robot limit of %s: %d robots (search took %.0f s)", name, limit, took)
        out[name] = limit
    return out
