"""Offline profiling of the VLM SM restriction: the lookup table behind guarded dynamic SM
partitioning.

For every (VLM architecture, VLM batch, action architecture, action batch) that can
co-occur in a lockstep, the profiler replays that lockstep on the GPU at every SM level
(multiples of 8 below the SM count, plus unrestricted) and keeps the fastest. It uses the
engine's own runner and graphs, so it times exactly what serving will run.

Then each action graph is tried planned for, or confined to, the SMs a restricted VLM leaves
free. A candidate that makes its same-model lockstep faster is timed in every combination
with that action and stored beside the plain graph's timings (``plan_actions``). An engine
uses it only where it makes the combinations of the models it serves faster in sum
(``SMTable.for_archs``): one graph serves every VLM partner, and a graph confined beside a
large VLM level can slow the locksteps with a smaller VLM beside it.

Tables are JSON, keyed by GPU name, torch version, max_batch and the architectures, cached
in a state directory and reused on later starts. Entries are keyed by ``profile_key``
(architecture and size), so fine-tuned variants of one architecture share them, and a
table for a superset of architectures serves any subset.

CLI: ``python -m services.executor.profiler --models pi0:full,smolvla:full --out bench/results/sm_table.json``
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import importlib
import json
import logging
import re
import statistics
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from services.executor.sm import SM_GRANULARITY, Level, level_name, parse_level
from shared.files import exclusive, write_atomic

log = logging.getLogger(__name__)

Combo = tuple[str, int, str, int]  # vlm arch, vlm batch, action arch, action batch


@dataclass
class ProfileEntry:
    vlm: str
    vlm_batch: int
    action: str
    action_batch: int
    best_sms: int | None  # None: unrestricted was fastest
    best_ms: float
    unrestricted_ms: float
    times_ms: dict[str, float] = field(default_factory=dict)  # level name -> median lockstep time

    @property
    def combo(self) -> Combo:
        return (self.vlm, self.vlm_batch, self.action, self.action_batch)


# How restricted graphs plan their GEMMs (graphs.gemm_sm_target). A table (or the disjoint
# engine's partition profile) timed with other captures chose for other kernels: it is
# profiled again, not reused.
GEMM_PLAN = "sm_target"


@dataclass
class SMTable:
    gpu: str
    sm_count: int
    torch: str
    max_batch: int
    archs: list[str]
    entries: list[ProfileEntry] = field(default_factory=list)
    profile_s: float = 0.0  # wall time of the profiling runs that produced the entries
    repeats: int = 0
    gemm_plan: str = ""  # GEMM_PLAN of the captures it was timed with; "" before there was one
    # "arch|batch" -> SMs that action graph's GEMMs are planned for (None: tried, no candidate
    # kept). A key is absent until it was tried.
    action_plans: dict[str, int | None] = field(default_factory=dict)
    # "arch|batch" -> VLM level whose free SMs that action graph is confined to (GEMMs planned
    # for them); such a key's action_plans value is None.
    action_confine: dict[str, int] = field(default_factory=dict)
    # "arch|batch" -> every combination with that action timed with its planned or confined
    # graph; ``entries`` hold the same combinations timed with the plain graph. A plan without
    # such entries comes from a table written before them, whose entries were timed with it.
    plan_entries: dict[str, list[ProfileEntry]] = field(default_factory=dict)

    def best_levels(self) -> dict[Combo, Level]:
        return {e.combo: e.best_sms for e in self.entries}

    def candidate(self, key: str) -> tuple[int | None, int | None]:
        return self.action_plans.get(key), self.action_confine.get(key)

    def plans(self) -> dict[str, tuple[int | None, int | None]]:
        """Action key -> (planned SMs, confined level) of every action graph tried."""
        return {k: self.candidate(k) for k in set(self.action_plans) | set(self.action_confine)}

    def timing_plans(self) -> dict[str, tuple[int | None, int | None]]:
        """Action key -> (planned SMs, confined level) of the graphs ``entries`` were timed with:
        the plain graph, except for plans from tables written before ``plan_entries``."""
        return {k: v for k, v in self.plans().items() if k not in self.plan_entries and v != (None, None)}

    def plan_totals(self, key: str, archs: set[str]) -> tuple[float, float, int]:
        """Summed best lockstep ms over the combinations with action ``key`` among ``archs``:
        (plain graph, candidate graph, how many combinations)."""
        plain = {e.combo: e.best_ms for e in self.entries if e.vlm in archs and e.action in archs}
        cand = [e for e in self.plan_entries.get(key, []) if e.combo in plain]
        return sum(plain[e.combo] for e in cand), sum(e.best_ms for e in cand), len(cand)

    def for_archs(self, archs: list[str]) -> "SMTable":
        """The table an engine serving ``archs`` uses: their entries, and each action graph
        planned or confined only where that makes their combinations with it faster in sum by
        ``PLAN_MIN_GAIN`` (each combination counted once: the engine cannot know in advance how
        often each VLM partner comes). Those combinations then carry the candidate's timings."""
        served = set(archs)
        entries = {e.combo: e for e in self.entries if e.vlm in served and e.action in served}
        plans: dict[str, int | None] = {}
        confine: dict[str, int] = {}
        for key, (plan, level) in sorted(self.plans().items()):
            if key.rpartition("|")[0] not in served:
                continue
            if key in self.plan_entries:
                plain, cand, n = self.plan_totals(key, served)
                with_action = sum(1 for e in entries.values() if action_key(e.action, e.action_batch) == key)
                # Used only where timed in every served combination with that action, and faster in sum.
                if not (n and n == with_action and cand < plain * (1 - PLAN_MIN_GAIN)):
                    plan, level = None, None
                else:
                    entries.update({e.combo: e for e in self.plan_entries[key] if e.combo in entries})
            plans[key] = plan
            if level is not None:
                confine[key] = level
        return dataclasses.replace(self, archs=sorted(served),
                                   entries=list(entries.values()), action_plans=plans, action_confine=confine,
                                   plan_entries={})

    def covers(self, combos: list[Combo]) -> bool:
        have = {e.combo for e in self.entries}
        return all(c in have for c in combos)

    def save(self, path: str | Path) -> None:
        """Write the table. Executors sharing one file (a cluster's engine.sm_table) profile their own
        architectures, maybe at the same time: under a lock on a file beside it, what the file already holds for
        the same GPU and torch is kept beside this table, or the last writer dropped the others' minutes of
        profiling (and they profiled again at every start)."""
        path = Path(path)
        with exclusive(path):
            merged = self
            try:
                there = SMTable.load(path) if path.exists() else None
            except TableError:
                there = None  # damaged: replaced
            if there is not None and _matches(there, self.gpu, self.torch, self.sm_count):
                merged = there.merged_with(self)
            write_atomic(path, json.dumps(dataclasses.asdict(merged), indent=1) + "\n")

    def merged_with(self, new: "SMTable") -> "SMTable":
        """This table with ``new``'s entries and action graphs added; where both have them, ``new``'s. An action
        graph is taken whole (its plan, confinement and candidate timings) from the table that last tried it."""
        entries = {e.combo: e for e in self.entries}
        entries.update({e.combo: e for e in new.entries})
        plans, confine, plan_entries = {}, {}, {}
        for key in set(self.plans()) | set(new.plans()) | set(self.plan_entries) | set(new.plan_entries):
            src = new if key in new.plans() or key in new.plan_entries else self
            if key in src.action_plans:
                plans[key] = src.action_plans[key]
            if key in src.action_confine:
                confine[key] = src.action_confine[key]
            if key in src.plan_entries:
                plan_entries[key] = src.plan_entries[key]
        return dataclasses.replace(new, archs=sorted(set(self.archs) | set(new.archs)), entries=list(entries.values()),
                                   action_plans=plans, action_confine=confine, plan_entries=plan_entries)

    @classmethod
    def load(cls, path: str | Path) -> "SMTable":
        """Read a table; TableError for a file that is unreadable or no SM table of this version (cut off by a full
        disk, a list, a key a newer version wrote, a level no green context can have). The executor reads it at
        every start and reload: a raw exception there was a crash loop."""
        try:
            data = json.loads(Path(path).read_text())
            data["entries"] = [_entry(e) for e in data.get("entries", [])]
            data["plan_entries"] = {k: [_entry(e) for e in v] for k, v in data.get("plan_entries", {}).items()}
            table = cls(**data)
        except (OSError, ValueError, TypeError, KeyError, AttributeError) as exc:
            raise TableError(f"{path} is no readable SM table ({type(exc).__name__}: {exc})") from None
        if not isinstance(table.sm_count, int) or isinstance(table.sm_count, bool):
            raise TableError(f"{path} is no readable SM table (sm_count {table.sm_count!r})")

        def level_ok(sms) -> bool:  # a level a green context can have (GreenStreams' check, which would raise)
            return (isinstance(sms, int) and not isinstance(sms, bool) and 0 < sms < table.sm_count
                    and sms % SM_GRANULARITY == 0)

        # Every level the engine may create a context for: the entries', and the confined action graphs' and their
        # timings' (for_archs serves those too). Only the entries' were checked, and a bad confined level then
        # stopped the executor at each start instead of being profiled again.
        bad = [e.combo for e in table.entries if e.best_sms is not None and not level_ok(e.best_sms)]
        bad += [e.combo for es in table.plan_entries.values() for e in es if e.best_sms is not None
                and not level_ok(e.best_sms)]
        bad += [k for k, v in table.action_confine.items() if not level_ok(v)]
        bad += [k for k, v in table.action_plans.items() if v is not None and not (
            isinstance(v, int) and not isinstance(v, bool) and 0 < v <= table.sm_count)]
        if bad:
            raise TableError(f"{path} is no readable SM table (SM levels of {bad[:3]} on {table.sm_count} SMs)")
        return table


class TableError(ValueError):
    """An SM table file that cannot be used: unreadable, or not a table of this version."""


def _entry(data: dict) -> ProfileEntry:
    e = ProfileEntry(**data)
    if not (isinstance(e.vlm, str) and isinstance(e.action, str) and isinstance(e.best_ms, (int, float))
            and isinstance(e.vlm_batch, int) and isinstance(e.action_batch, int) and isinstance(e.times_ms, dict)):
        raise TypeError(f"entry {data!r:.120} has a field of the wrong type")
    return e


def combos_for(archs: list[str], batch_sizes: list[int]) -> list[Combo]:
    return [(va, vb, aa, ab) for va in archs for vb in batch_sizes for aa in archs for ab in batch_sizes]


def missing_combos(table: SMTable, archs: list[str], batch_sizes: list[int]) -> list[Combo]:
    have = {e.combo for e in table.entries}
    return [c for c in combos_for(archs, batch_sizes) if c not in have]


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9.+-]+", "_", text).strip("_")


def table_path(profile_dir: str | Path, gpu: str, torch_version: str, max_batch: int, archs: list[str]) -> Path:
    arch_part = "+".join(sorted(archs))
    if len(arch_part) > 80:
        arch_part = hashlib.sha1(arch_part.encode()).hexdigest()[:12]
    return Path(profile_dir) / f"sm-table_{_slug(gpu)}_torch{_slug(torch_version)}_mb{max_batch}_{_slug(arch_part)}.json"


def _matches(table: SMTable, gpu: str, torch_version: str, sm_count: int) -> bool:
    # The SM count too: one GPU name covers parts with fewer SMs (a MIG slice, a cut-down board).
    return (table.gpu == gpu and table.torch == torch_version and table.gemm_plan == GEMM_PLAN
            and table.sm_count == sm_count)


def _load_or_warn(path: Path) -> SMTable | None:
    """The table at ``path``, or None with a warning: a damaged table is profiled again, never fatal."""
    try:
        return SMTable.load(path)
    except TableError as exc:
        log.warning("%s: profiling anew", exc)
        return None


def _action_changed(table: SMTable, entry: ProfileEntry) -> bool:
    """Whether ``entry`` was timed with a planned or confined action graph (older tables)."""
    return action_key(entry.action, entry.action_batch) in table.timing_plans()


def locate_table(device: torch.device, archs: list[str], max_batch: int, sm_table: str | None,
                 profile_dir: str) -> tuple[Path, SMTable]:
    """The table to use and where to save it: the configured file, the cached one for this
    key, or a new one seeded with the entries of any cached table from the same GPU and torch."""
    gpu, version = torch.cuda.get_device_name(device), torch.__version__
    fresh = SMTable(gpu, torch.cuda.get_device_properties(device).multi_processor_count, version, max_batch,
                    sorted(archs), gemm_plan=GEMM_PLAN)
    batch_sizes = [1 << i for i in range(max_batch.bit_length())]
    wanted = combos_for(sorted(archs), batch_sizes)
    sms = fresh.sm_count
    if sm_table:
        path = Path(sm_table)
        if path.exists():
            table = _load_or_warn(path)
            if table is not None and _matches(table, gpu, version, sms):
                return path, table
            if table is not None:
                log.warning("%s was profiled on %s (%s SMs) / torch %s / GEMM plan %r, not %s (%d SMs) / torch %s / "
                            "%r: profiling anew into %s", path, table.gpu, table.sm_count, table.torch, table.gemm_plan,
                            gpu, sms, version, GEMM_PLAN, profile_dir)
        else:
            return path, fresh
    path = table_path(profile_dir, gpu, version, max_batch, archs)
    if path.exists():
        cached = _load_or_warn(path)
        if cached is not None and _matches(cached, gpu, version, sms):
            return path, cached
        if cached is not None:
            log.warning("%s was timed with other VLM captures (GEMM plan %r, %s SMs): profiling it again", path,
                        cached.gemm_plan, cached.sm_count)
    for other in sorted(Path(profile_dir).glob("sm-table_*.json")):
        if other == path or not other.is_file():
            continue
        try:
            table = SMTable.load(other)
        except TableError:
            log.warning("ignoring unreadable SM table %s", other)
            continue
        if _matches(table, gpu, version, sms):
            # Only entries timed with the action graph as torch captures it: one timed with a
            # planned or confined graph would be served with another (the new table has no
            # plans yet), so it is profiled again.
            fresh.entries += [e for e in table.entries if e.combo in wanted and e.combo not in
                              {x.combo for x in fresh.entries} and not _action_changed(table, e)]
    if fresh.entries:
        log.info("reusing %d cached SM table entries from %s", len(fresh.entries), profile_dir)
    return path, fresh


def lockstep_samples(runner, vst, vb: int, ast, ab: int, level: Level, repeats: int, warmup: int = 2) -> list:
    """The runner's timings of ``repeats`` locksteps (after ``warmup`` runs): ``ast``'s action
    stage at batch ``ab`` beside ``vst``'s VLM stage at batch ``vb`` on ``level`` SMs."""
    samples = []
    for i in range(warmup + repeats):
        runner.begin(i)
        runner.launch_handoff(ast, ab)
        runner.launch_action(ast, ab, 0)
        runner.launch_vlm(vst, vb, level, after_handoff=ast is vst and ab == vb)
        runner.end_launch()
        runner.wait()
        if i >= warmup:
            samples.append(runner.measure(i, False))
    return samples


def time_lockstep(runner, vst, vb: int, ast, ab: int, level: Level, repeats: int, warmup: int = 2) -> float:
    """Median duration (ms) of that lockstep (``lockstep_samples``)."""
    return statistics.median(t.duration_ms for t in lockstep_samples(runner, vst, vb, ast, ab, level, repeats, warmup))


def time_entry(runner, by_arch: dict, combo: Combo, levels: list[Level], repeats: int, warmup: int,
               bar=None) -> ProfileEntry:
    """Time one combo at every level with the architectures' current graphs; keep the fastest."""
    va, vb, aa, ab = combo
    times: dict[str, float] = {}
    for level in levels:
        times[level_name(level)] = time_lockstep(runner, by_arch[va], vb, by_arch[aa], ab, level, repeats, warmup)
        if bar is not None:
            bar.update()
    best = min(levels, key=lambda lv: times[level_name(lv)])
    return ProfileEntry(va, vb, aa, ab, best, times[level_name(best)], times["none"], times)


def profile(by_arch: dict, runner, batch_sizes: list[int], levels: list[Level], combos: list[Combo],
            table: SMTable, repeats: int = 5, warmup: int = 2, progress: bool = True,
            total_sms: int | None = None) -> SMTable:
    """Time every combo at every level with the engine's runner; add the entries to ``table``.

    ``by_arch`` maps an architecture key to one ``GraphStages`` of it (graphs and buffers
    allocated); VLM graphs for all ``levels`` are captured here as they are needed. With
    ``total_sms`` (the GPU's SM count), action graphs are then tried planned for fewer SMs
    (``plan_actions``).
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    groups: dict[tuple[str, int], list[tuple[str, int]]] = {}
    for va, vb, aa, ab in combos:
        groups.setdefault((va, vb), []).append((aa, ab))
    bar = tqdm(total=len(combos) * len(levels), desc="SM profile", unit="run", disable=not progress)
    done = {e.combo for e in table.entries}
    for (va, vb), actions in groups.items():
        vst = by_arch[va]
        vst.capture_vlm(vb, set(levels))
        for aa, ab in actions:
            entry = time_entry(runner, by_arch, (va, vb, aa, ab), levels, repeats, warmup, bar)
            best = entry.best_sms
            if entry.combo in done:
                table.entries = [e for e in table.entries if e.combo != entry.combo]
            table.entries.append(entry)
            bar.set_postfix_str(f"{va}x{vb}|{aa}x{ab} best {level_name(best)}")
    if total_sms:
        plan_actions(by_arch, runner, levels, combos, table, total_sms, repeats, warmup, bar)
    bar.close()
    table.archs = sorted(set(table.archs) | set(by_arch))
    table.max_batch = max([table.max_batch, *batch_sizes])  # a table extended for a larger max_batch says so
    table.profile_s += time.perf_counter() - t0
    table.repeats = repeats
    return table


PLAN_MIN_GAIN = 0.01  # a planned or confined action graph is kept only when its lockstep is this much faster
CONFINE_MIN_SMS = 20  # smallest partition an action graph is confined to (cuBLAS failed on 12 SMs on an H100)
CANDIDATE_WITHIN = 1.2  # levels tried: where the same-model lockstep was within this factor of its best


def action_key(arch: str, batch: int) -> str:
    return f"{arch}|{batch}"


def plan_actions(by_arch: dict, runner, levels: list[Level], combos: list[Combo], table: SMTable, total_sms: int,
                 repeats: int = 5, warmup: int = 2, bar=None) -> None:
    """Try each action graph planned for, or confined to, the SMs a restricted VLM leaves free.

    Profiled as captured, an action graph plans its GEMMs for the whole GPU and may run on
    any SM. For each (action arch, batch) whose same-model lockstep (``(a, b, a, b)``, the
    common one when a model serves alone) is best restricted, and each level L where that
    lockstep was within ``CANDIDATE_WITHIN`` of its best, two graphs are tried in it with
    the VLM at L:

    - planned: on the plain action stream, GEMMs planned for ``total_sms - L``;
    - confined: on the SMs a VLM at L leaves free (``GreenStreams.complement``), GEMMs
      planned for them, where they are at least ``CONFINE_MIN_SMS``.

    The fastest is timed again at every level and kept as a candidate if it beats the profiled
    graph by ``PLAN_MIN_GAIN``; every profiled combination with that action is then timed
    with it at every level, into ``table.plan_entries``. The plain graph is restored either
    way, and ``table.entries`` keep its timings: whether an engine uses the candidate depends
    on which models it serves (``SMTable.for_archs``). One graph per (arch, batch) serves every
    VLM partner: the engine issues the action stage ahead, before it knows which VLM runs
    beside it. Only (arch, batch) pairs whose every table entry is in ``combos`` are tried
    (others would keep entries timed with another graph). A candidate from an earlier run
    is timed in the new combinations with its action instead. Results go to
    ``table.action_plans``, ``table.action_confine`` and ``table.plan_entries``.
    """
    by_action: dict[tuple[str, int], list[Combo]] = {}
    for c in combos:
        by_action.setdefault((c[2], c[3]), []).append(c)
    entries = {e.combo: e for e in table.entries}
    for (aa, ab), own in sorted(by_action.items()):
        key = action_key(aa, ab)
        diag = entries.get((aa, ab, aa, ab))
        ast = by_arch[aa]
        if not hasattr(ast, "replan_action"):
            continue
        if key in table.plan_entries:  # an earlier candidate: time it in the new combinations too
            have = {e.combo for e in table.plan_entries[key]}
            todo = [c for c in own if c not in have]
            if todo:
                plan, confine = table.candidate(key)
                try:
                    ast.replan_action(ab, plan, confine=confine)
                    table.plan_entries[key] += [time_entry(runner, by_arch, c, levels, repeats, warmup, bar)
                                                for c in todo]
                except RuntimeError as exc:  # it cannot be weighed over every combination: dropped
                    log.warning("%s x%d action candidate cannot run here, dropped: %s", aa, ab,
                                str(exc).splitlines()[0][:200])
                    del table.plan_entries[key]
                    table.action_plans[key] = None
                    table.action_confine.pop(key, None)
                ast.replan_action(ab, None)
            continue
        if key in table.action_plans or diag is None or diag.combo not in own:
            continue
        if any(e.combo[2:] == (aa, ab) and e.combo not in own for e in table.entries):
            continue
        table.action_plans[key] = None
        if diag.best_sms is None:
            continue

        def timed(level: Level) -> float:
            if bar is not None:
                bar.update()
            return time_lockstep(runner, ast, ab, ast, ab, level, repeats, warmup)

        def retime(combo: Combo) -> ProfileEntry:
            return time_entry(runner, by_arch, combo, levels, repeats, warmup, bar)

        near = [lv for lv in levels if lv is not None
                and diag.times_ms.get(level_name(lv), float("inf")) <= CANDIDATE_WITHIN * diag.best_ms]
        tries = [(total_sms - lv, None, lv) for lv in near if total_sms - lv >= SM_GRANULARITY] + \
                [(None, lv, lv) for lv in near if total_sms - lv >= CONFINE_MIN_SMS]
        if bar is not None:
            bar.total += len(tries)
        candidates: list[tuple[float, int | None, int | None]] = []  # (ms, planned SMs, confined level)
        for plan, confine, lv in tries:
            if bar is not None:
                bar.set_postfix_str(f"action {aa}x{ab} " + (f"beside VLM on {lv} SMs" if confine else
                                                          f"planned for {plan} SMs"))
            try:
                ast.replan_action(ab, plan, confine=confine)
                candidates.append((timed(lv), plan, confine))
            except RuntimeError as exc:  # a library kernel that cannot run on so few SMs
                log.warning("%s x%d action %s cannot run: %s", aa, ab, f"planned {plan}, confined {confine}",
                            str(exc).splitlines()[0][:200])  # replan_action dropped the old graph first
        if not candidates:
            ast.replan_action(ab, None)
            continue
        ms, plan, confine = min(candidates, key=lambda c: c[0])
        kept = ms < diag.best_ms * (1 - PLAN_MIN_GAIN)
        what = f"confined beside a VLM on {confine} SMs" if confine is not None else f"planned for {plan} SMs"
        log.info("%s x%d action %s: same-model lockstep %.3f ms against %.3f: %s (tried %s)", aa, ab, what, ms,
                 diag.best_ms, "kept" if kept else "not kept",
                 ", ".join(f"{'c' + str(c) if c else 'p' + str(p)} {m:.3f}" for m, p, c in candidates))
        if not kept:
            ast.replan_action(ab, None)
            continue
        ast.replan_action(ab, plan, confine=confine)
        if bar is not None:
            bar.total += len(levels) * len(own)
        planned = {diag.combo: retime(diag.combo)}
        if planned[diag.combo].best_ms >= diag.best_ms * (1 - PLAN_MIN_GAIN):  # its one timing was luck
            log.info("%s x%d action: %.3f ms timed again at every level, not kept", aa, ab,
                     planned[diag.combo].best_ms)
            ast.replan_action(ab, None)
            continue
        planned.update({c: retime(c) for c in own if c != diag.combo})
        ast.replan_action(ab, None)
        table.plan_entries[key] = list(planned.values())
        if confine is not None:
            table.action_confine[key] = confine
        else:
            table.action_plans[key] = plan
        plain_ms, cand_ms, n = table.plan_totals(key, set(table.archs) | set(by_arch))
        log.info("%s x%d action %s: a candidate; over its %d combinations %.3f ms against %.3f plain", aa, ab,
                 what, n, cand_ms, plain_ms)


def format_table(table: SMTable) -> str:
    lines = [f"SM table: {table.gpu} ({table.sm_count} SMs), torch {table.torch}, max_batch {table.max_batch}, "
             f"profiled in {table.profile_s:.1f} s",
             f"{'vlm':>18} {'b':>2} {'action':>18} {'b':>2} {'best SMs':>8} {'best ms':>8} {'unrestr ms':>10} {'gain':>6}"]
    for e in sorted(table.entries, key=lambda e: e.combo):
        lines.append(f"{e.vlm:>18} {e.vlm_batch:>2} {e.action:>18} {e.action_batch:>2} {level_name(e.best_sms):>8} "
                     f"{e.best_ms:>8.3f} {e.unrestricted_ms:>10.3f} {e.unrestricted_ms / e.best_ms:>5.2f}x")
    planned = {k: v for k, v in sorted(table.action_plans.items()) if v is not None}
    if planned:
        lines.append("action graphs planned for fewer SMs: " + ", ".join(f"{k} {v}" for k, v in planned.items()))
    if table.action_confine:
        lines.append("action graphs confined beside a VLM level: "
                     + ", ".join(f"{k} {v}" for k, v in sorted(table.action_confine.items())))
    used = table.for_archs(table.archs)
    plain = {e.combo: e.best_ms for e in table.entries}
    for key in sorted(table.plan_entries):
        total_plain, total_cand, n = table.plan_totals(key, set(table.archs))
        same = [f"; same-model {e.best_ms:.3f} ms against {plain[e.combo]:.3f}" for e in table.plan_entries[key]
                if e.vlm == e.action and e.vlm_batch == e.action_batch and e.combo in plain]
        use = "used" if used.candidate(key) != (None, None) else "not used"
        lines.append(f"candidate {key}: {n} combinations {total_cand:.3f} ms against {total_plain:.3f}"
                     f"{''.join(same)}; {use} serving all {len(table.archs)} models")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    from services.executor.engine import ServedModel
    from services.executor.lockstep import LockstepEngine
    from shared.config import EngineConfig
    from shared.models import build_model

    ap = argparse.ArgumentParser(description="Profile the VLM SM restriction table for co-located models")
    ap.add_argument("--models", required=True, help="comma-separated arch:size (e.g. pi0:full,smolvla:full)")
    ap.add_argument("--max-batch", type=int, default=2)
    ap.add_argument("--out", required=True, help="table JSON to write (reused when it already covers the models)")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--import", dest="imports", action="append", default=[],
                    help="module registering extra architectures (e.g. bench.models)")
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    for mod in args.imports:
        importlib.import_module(mod)
    device = torch.device(args.device)
    models = {}
    for spec in args.models.split(","):
        arch, _, size = spec.partition(":")
        models[spec] = ServedModel(spec, build_model(arch, size or "full", device=device), 1.0)
    cfg = EngineConfig(kind="robion", max_batch=args.max_batch, sm_table=args.out, profile_repeats=args.repeats)
    engine = LockstepEngine(models, cfg, device, lambda results: None)
    t0 = time.perf_counter()
    engine.prepare()
    log.info("start-up with profiling took %.1f s", time.perf_counter() - t0)
    # The engine's table: --out, or, when --out holds a table of another GPU or torch (refused with a warning),
    # the one it profiled into the profile directory instead.
    path = engine.table_path or Path(args.out)
    print(f"SM table file: {path}")
    print(format_table(SMTable.load(path)))
    print(f"prepare: {json.dumps({k: round(v, 2) for k, v in engine.prepare_s.items()})}")


if __name__ == "__main__":
    main()


__all__ = ["SMTable", "ProfileEntry", "locate_table", "missing_combos", "plan_actions", "profile", "parse_level",
           "time_lockstep"]
