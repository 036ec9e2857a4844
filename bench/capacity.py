"""Robot capacity per (model, engine) on one device: the paper's single-GPU experiment.

Simulated robots run in-process against each engine (services/executor/simulation.py);
the engines being compared run side by side in this process, their points interleaved
(one point of each engine in turn) so all see the same machine state. Capacity is the
largest robot count with SLO attainment >= --target (default 0.98).

    python bench/capacity.py --models pi0,xr0 --engines robion,monolithic --size full \\
        --device cuda:0 --hz 2 --epochs 5 --duration 10 --max-batch 2 \\
        --out bench/results/capacity_single_gpu.json --plot bench/results/capacity_single_gpu.png

Engines: a kind (``robion``), or ``label=kind:field=value:...`` with EngineConfig
overrides, e.g. ``static=robion:sm_policy=static:static_sms=66`` or ``mb1=robion:max_batch=1``.
Models: architecture names (``pi0``), or ``name=arch`` for several of one architecture.
The JSON is rewritten after every point, so an interrupted run keeps what it measured;
--merge keeps other models' results already in --out (run models one command each).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import logging
import math
import os
import platform
import subprocess
import sys
import types
import typing
from pathlib import Path
from typing import Any

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

from services.executor.simulation import (PAPER_DEADLINES_MS, LAG_LIMIT, CapacityResult, EngineHost, Point,  # noqa: E402
                                          SimConfig, _json_safe, compare_capacity, engine_factory,
                                          served_models)
from shared.config import NETWORKS  # noqa: E402
from shared.files import write_atomic  # noqa: E402
from shared.service import log_level  # noqa: E402

SCHEMA = "robion.capacity/1"
log = logging.getLogger("bench.capacity")


@dataclasses.dataclass
class EngineSpec:
    label: str
    kind: str
    overrides: dict[str, Any]


def _parse_value(field_type: Any, text: str) -> Any:
    tp = field_type
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        if text.lower() in ("none", "null"):
            return None
        tp = next(a for a in typing.get_args(tp) if a is not type(None))
    if tp is bool:
        if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
            raise ValueError(f"expected true or false, got {text!r}")
        return text.lower() in ("true", "1", "yes")
    if tp in (int, float, str):
        return tp(text)
    return text


def parse_engines(text: str, max_batch: int) -> list[EngineSpec]:
    """``robion,static=robion:sm_policy=static:static_sms=64`` -> engine specs with typed EngineConfig overrides,
    checked as a config file's `engine:` is (a max_batch of 0 or 3, an unknown kind: refused, not measured)."""
    from shared.config import ConfigError, EngineConfig, engine_config

    hints = typing.get_type_hints(EngineConfig)
    specs: list[EngineSpec] = []
    for item in filter(None, (s.strip() for s in text.split(","))):
        head = item.split(":")[0]
        label, rest = item.split("=", 1) if "=" in head else (head, item)
        parts = rest.split(":")
        kind, opts = parts[0], parts[1:]
        overrides: dict[str, Any] = {"max_batch": max_batch}
        for opt in opts:
            key, eq, value = opt.partition("=")
            if not eq or key not in hints or key == "kind":
                raise SystemExit(f"--engines {item!r}: {opt!r} is not field=value of EngineConfig "
                                 f"(fields: {', '.join(k for k in hints if k != 'kind')})")
            try:
                overrides[key] = _parse_value(hints[key], value)
            except ValueError as exc:
                raise SystemExit(f"--engines {item!r}: {key}: {exc}") from None
        if any(s.label == label for s in specs):
            raise SystemExit(f"--engines: label {label!r} is used twice")
        try:
            engine_config({"kind": kind, **overrides})
        except ConfigError as exc:
            raise SystemExit(f"--engines {item!r}: {exc}") from None
        specs.append(EngineSpec(label, kind, overrides))
    if not specs:
        raise SystemExit("--engines: at least one engine is needed")
    return specs


def parse_models(text: str) -> dict[str, str]:
    out: dict[str, str] = {}
    for item in filter(None, (s.strip() for s in text.split(","))):
        name, _, arch = item.partition("=")
        out[name] = arch or name
    if not out:
        raise SystemExit("--models: at least one model is needed")
    return out


def parse_deadlines(text: str | None) -> dict[str, float]:
    out: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in (text or "").split(","))):
        key, eq, ms = item.partition("=")
        try:
            value = float(ms) if eq else math.nan
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value > 0):
            raise SystemExit(f"--deadline {item!r}: expected name=ms with a positive number of milliseconds")
        out[key] = value
    return out


def _git(*args: str) -> str | None:
    try:
        return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, timeout=10,
                              check=True).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return None


def source_commit(short: bool = False) -> str | None:
    """The commit the measured code came from.

    A copy of the tree shipped to a GPU host names its commit in ROBION_COMMIT: its own
    .git, if it has one, need not be the one the tree came from.
    """
    return os.environ.get("ROBION_COMMIT") or _git("rev-parse", *(["--short"] if short else []), "HEAD")


def dirty() -> bool | None:
    """Whether the measured tree differs from its commit; None when that cannot be told.

    A copy shipped with ROBION_COMMIT names its state in ROBION_DIRTY (1 or 0): its own .git, if any, need
    not match the tree. Without git, None: a copy whose state is unknown is not recorded as clean.
    """
    if os.environ.get("ROBION_COMMIT"):
        flag = os.environ.get("ROBION_DIRTY")
        return None if flag is None else flag not in ("", "0")
    status = _git("status", "--porcelain", "--untracked-files=no")
    return None if status is None else bool(status)


def meta(device: str) -> dict:
    import torch

    gpu = None
    if device.startswith("cuda") and torch.cuda.is_available():
        gpu = torch.cuda.get_device_name(torch.device(device))
    return {
        "gpu": gpu, "device": device, "cpu": platform.processor() or platform.machine(), "host": platform.node(),
        "date": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "commit": source_commit(),
        "dirty": dirty(),
        "command": " ".join([os.path.relpath(sys.argv[0], ROOT) if sys.argv[0] else "bench/capacity.py",
                             *sys.argv[1:]]),
        "python": platform.python_version(), "torch": torch.__version__,
        "cuda": torch.version.cuda,
    }


def _point_dict(p: Point) -> dict:
    return _json_safe(dataclasses.asdict(p))


# What makes capacities comparable side by side in one file (and one plot, titled with one GPU): runs merged into a
# file must agree on these. Durations, epochs and search starts may differ per model (E1 sets them per model).
MERGE_SETTINGS = ("hz", "network", "max_batch", "size")


class Report:
    """The JSON document; rewritten after every point so an interrupted run keeps its points."""

    def __init__(self, path: Path | None, settings: dict, meta_: dict, merge: bool):
        self.path = path
        # A model is this run's from its first point on (point()): one interrupted before it stays the earlier run's.
        self._models = dict(settings.get("models") or {})
        self.doc: dict = {"schema": SCHEMA, "target": settings["target"], "capacity": {}, "capped": {}, "complete": {},
                          "ratios": {}, "deadlines_ms": {}, "curves": {}, "settings": {**settings, "models": {}},
                          "meta": meta_}
        self._fresh: set[str] = set()  # models this run has measured a point of
        if merge and path is not None and path.exists():
            old = json.loads(path.read_text())
            if old.get("schema") != SCHEMA:
                raise SystemExit(f"--merge: {path} is not a {SCHEMA} file")
            if old.get("target") != settings["target"]:
                # One top-level target: the kept models' capacities would read as measured at this run's.
                raise SystemExit(f"--merge: {path} holds capacities at target {old.get('target')}, this run "
                                 f"measures at {settings['target']}; write another file")
            was = {**{k: (old.get("settings") or {}).get(k) for k in MERGE_SETTINGS},
                   "gpu": (old.get("meta") or {}).get("gpu")}
            now = {**{k: settings.get(k) for k in MERGE_SETTINGS}, "gpu": meta_.get("gpu")}
            differ = [f"{k} {was[k]!r} there, {now[k]!r} here" for k in was if was[k] != now[k]]
            if differ:
                raise SystemExit(f"--merge: {path} was measured otherwise ({'; '.join(differ)}): its capacities "
                                 "would not compare with this run's; write another file")
            for key in ("capacity", "capped", "complete", "ratios", "deadlines_ms", "curves", "overlap_bound"):
                self.doc[key] = old.get(key, {})
            # Settings and meta of earlier runs stay with the models they measured (settings.models).
            self.doc["runs"] = [*old.get("runs", []), {"settings": old.get("settings"), "meta": old.get("meta")}]

    def point(self, model: str, engine: str, point: Point) -> None:
        if model not in self._fresh:
            # A model measured again replaces its earlier results as a whole, from its first point on: an
            # interrupted rerun must not leave new points on the old curves beside the old capacities. (Its
            # deadline and overlap bound are this run's already: written before its first point.)
            self._fresh.add(model)
            for key in ("capacity", "capped", "complete", "ratios", "curves"):
                self.doc.get(key, {}).pop(model, None)
            # Nor may an earlier run still claim it (settings.models): one run describes each model's results.
            for run in self.doc.get("runs", []):
                ((run.get("settings") or {}).get("models") or {}).pop(model, None)
            if "runs" in self.doc:
                self.doc["runs"] = [r for r in self.doc["runs"] if (r.get("settings") or {}).get("models")]
            self.doc["settings"]["models"][model] = self._models.get(model)
        self.doc["curves"].setdefault(model, {}).setdefault(engine, []).append(_point_dict(point))
        self.doc["complete"].setdefault(model, {})[engine] = False
        self.write()

    def model_done(self, model: str, results: dict[str, CapacityResult], baseline: str | None) -> None:
        self.doc["capacity"][model] = {e: r.capacity for e, r in results.items()}
        # Capacities at --max-robots are lower bounds: such a ratio would read as a measured one.
        self.doc.setdefault("capped", {})[model] = {e: r.capped for e, r in results.items()}
        self.doc["complete"][model] = {e: True for e in results}
        self.doc["curves"][model] = {e: [_point_dict(p) for p in sorted(r.points, key=lambda p: p.robots)]
                                     for e, r in results.items()}
        # Replaced as a whole, like the capacities: ratios of an earlier run (--merge) against engines this run
        # did not measure would contradict them.
        self.doc["ratios"].pop(model, None)
        if baseline in results:
            base = results[baseline].capacity
            self.doc["ratios"][model] = {f"{e}/{baseline}": (r.capacity / base if base and not
                                                             (r.capped or results[baseline].capped) else None)
                                         for e, r in results.items() if e != baseline}
        self.write()

    def write(self) -> None:
        if self.path is None:
            return
        write_atomic(self.path, json.dumps(_json_safe(self.doc), indent=1) + "\n")


def overlap_bound(model, batch: int, device: str) -> dict:
    """Solo stage times at ``batch`` and the most any overlap can gain: (T_vlm + T_act) / max(T_vlm, T_act).

    On a GPU from CUDA-graph replays (bench/model_latency.py); on the CPU from eager runs.
    """
    import statistics
    import time

    import torch

    if device.startswith("cuda"):
        sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
        from model_latency import bench_batch

        with torch.cuda.device(torch.device(device)):
            r = bench_batch(model, batch, iters=50, warmup=10)
        vlm, act = r["vlm_ms"]["median"], r["action_ms"]["median"]
    else:
        images, state, tokens = model.example_inputs(batch, device=device)
        noise = model.noise(batch, device=device)
        v, a = [], []
        with torch.inference_mode():
            for _ in range(7):
                t0 = time.perf_counter()
                h = model.vlm_stage(images, state, tokens)
                t1 = time.perf_counter()
                model.action_stage(h, noise)
                t2 = time.perf_counter()
                v.append((t1 - t0) * 1e3)
                a.append((t2 - t1) * 1e3)
        vlm, act = statistics.median(v[2:]), statistics.median(a[2:])
    return {"batch": batch, "vlm_ms": vlm, "action_ms": act, "bound": (vlm + act) / max(vlm, act)}


def plot(doc: dict, path: Path) -> bool:
    """SLO attainment and p99 against robots: one column per model, one line per engine."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        import matplotlib.ticker
    except ImportError:
        log.warning("matplotlib is not installed: no plot written to %s", path)
        return False
    models = list(doc["curves"])
    if not models:
        return False
    fig, axes = plt.subplots(2, len(models), figsize=(4.2 * len(models), 6.4), squeeze=False, sharex="col")
    target = doc["target"]
    deadlines = doc.get("deadlines_ms", {})
    for j, model in enumerate(models):
        ax_slo, ax_p99 = axes[0][j], axes[1][j]
        for engine, pts in doc["curves"][model].items():
            # A count measured twice (screened, then in full): the full run, whose verdict the search took,
            # even where it stopped early after as few epochs as screening ran; else the longer run.
            def rank(p: dict) -> tuple[bool, int]:
                return not p.get("screened", False), p["epochs"]

            best: dict[int, dict] = {}
            for pt in pts:
                if pt["robots"] not in best or rank(pt) > rank(best[pt["robots"]]):
                    best[pt["robots"]] = pt
            pts = sorted(best.values(), key=lambda p: p["robots"])
            xs = [p["robots"] for p in pts]
            cap = doc["capacity"].get(model, {}).get(engine)
            capped = (doc.get("capped") or {}).get(model, {}).get(engine)
            label = f"{engine} (cap {'>= ' if capped else ''}{cap})" if cap is not None else engine
            line, = ax_slo.plot(xs, [100 * (p["slo_attainment"] or 0.0) for p in pts], marker="o", ms=3, label=label)
            ax_p99.plot(xs, [p["p99_ms"] if p["p99_ms"] is not None else float("nan") for p in pts],
                        marker="o", ms=3, color=line.get_color(), label=engine)
        ax_slo.axhline(100 * target, color="grey", ls="--", lw=0.8)
        ax_slo.set_title(model)
        ax_slo.set_ylabel("SLO attainment (%)")
        ax_slo.set_ylim(-2, 102)
        ax_slo.legend(fontsize=7)
        if model in deadlines:
            ax_p99.axhline(deadlines[model], color="grey", ls="--", lw=0.8)
        ax_p99.set_ylabel("p99 end-to-end latency (ms)")
        ax_p99.set_yscale("log")  # overloaded points reach seconds; the deadline region must stay readable
        ax_p99.yaxis.set_major_locator(matplotlib.ticker.LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
        ax_p99.yaxis.set_major_formatter(matplotlib.ticker.ScalarFormatter())
        ax_p99.yaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax_p99.set_xlabel("robots")
    meta_ = doc.get("meta", {})
    fig.suptitle(f"capacity at {100 * target:.0f}% SLO attainment - {meta_.get('gpu') or meta_.get('device')}",
                 fontsize=9)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def bad_arguments(args: argparse.Namespace, robots: list[int] | None) -> str | None:
    """What is wrong with the measurement arguments, if anything: found before minutes of model building."""
    if not (math.isfinite(args.hz) and args.hz > 0):
        return f"--hz: expected a positive rate, got {args.hz}"
    if args.epochs < 1:
        return f"--epochs: expected at least 1, got {args.epochs}"
    if not (math.isfinite(args.duration) and args.duration >= 1 / args.hz):
        # Shorter, and a robot whose random start falls after the window sends nothing: points without requests.
        return f"--duration: expected at least one period (1 / --hz = {1 / args.hz:g} s), got {args.duration}"
    if not (math.isfinite(args.drain) and args.drain >= 0):
        return f"--drain: expected a non-negative number of seconds, got {args.drain}"
    if not 0 < args.target <= 1:
        return f"--target: expected a share in (0, 1], got {args.target}"
    if args.screen_epochs < 0:
        return f"--screen-epochs: expected 0 or more, got {args.screen_epochs}"
    if args.start < 1 or args.max_robots < args.start:
        return f"--start and --max-robots: expected 1 <= start <= max-robots, got {args.start} and {args.max_robots}"
    if robots is not None and (not robots or min(robots) < 1):
        return f"--sweep: expected robot counts of at least 1, got {args.sweep!r}"
    if args.seed < 0:  # numpy's SeedSequence refuses it, after the models and the overlap bound are built
        return f"--seed: expected a non-negative integer, got {args.seed}"
    if args.network not in NETWORKS:
        return f"--network: expected one of {', '.join(NETWORKS)}, got {args.network!r}"
    return None


def unknown_models(models: dict[str, str], size: str) -> str | None:
    """An architecture that is not registered or has no such size: found before any model is built."""
    from shared.models import get_architecture

    for name, arch in models.items():
        try:
            sizes = get_architecture(arch).CONFIGS
        except KeyError as exc:
            return f"--models {name}: {exc.args[0] if exc.args else exc}"
        if size not in sizes:
            return f"--size: {arch} has no size {size!r}; sizes: {', '.join(sorted(sizes))}"
    return None


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", help="comma-separated architectures, or name=arch (required unless --replot)")
    p.add_argument("--engines", default="robion,monolithic",
                   help="comma-separated engine kinds, or label=kind:field=value:... (EngineConfig overrides)")
    p.add_argument("--size", default="full", help="model size: full or tiny")
    p.add_argument("--device", default="cuda:0")
    p.add_argument("--hz", type=float, default=2.0)
    p.add_argument("--epochs", type=int, default=5)
    p.add_argument("--duration", type=float, default=10.0, help="seconds of sending per epoch")
    p.add_argument("--drain", type=float, default=1.0, help="seconds after each epoch for the last replies")
    p.add_argument("--max-batch", type=int, default=2)
    p.add_argument("--target", type=float, default=0.98)
    p.add_argument("--network", default="wifi7")
    p.add_argument("--deadline", help="deadline overrides, name=ms or arch=ms, comma-separated "
                                      f"(default: the paper's, {PAPER_DEADLINES_MS})")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--start", type=int, default=1, help="first robot count of the search")
    p.add_argument("--max-robots", type=int, default=256)
    p.add_argument("--screen-epochs", type=int, default=1,
                   help="search: epochs of the bracketing points; the candidate and the count above it run "
                        "all --epochs (0: every point runs all epochs)")
    p.add_argument("--sweep", help="comma-separated robot counts: measure each (all epochs) instead of searching")
    p.add_argument("--no-early-stop", action="store_true",
                   help="search: run every epoch even once a point can no longer pass")
    p.add_argument("--no-reuse", action="store_true", help="build and prepare a fresh engine for every point")
    p.add_argument("--baseline", help="engine the ratios are taken against (default: monolithic when given)")
    p.add_argument("--out", type=Path, help="JSON results file")
    p.add_argument("--merge", action="store_true", help="keep other models' results already in --out")
    p.add_argument("--plot", type=Path, help="PNG of the curves (needs matplotlib)")
    p.add_argument("--replot", type=Path, metavar="JSON", help="measure nothing: draw --plot from this results file")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--log-level", type=log_level, default="WARNING")
    args = p.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if args.replot:
        if not args.plot:
            raise SystemExit("--replot needs --plot PNG")
        try:
            doc = json.loads(args.replot.read_text())
        except (OSError, ValueError) as exc:
            raise SystemExit(f"--replot: cannot read {args.replot}: {exc}") from None
        if not isinstance(doc, dict) or doc.get("schema") != SCHEMA:
            raise SystemExit(f"--replot: {args.replot} is not a {SCHEMA} file")
        if not plot(doc, args.plot):
            raise SystemExit(f"no plot written (matplotlib missing or no curves in {args.replot})")
        print(f"wrote {args.plot}")
        return 0
    if not args.models:
        raise SystemExit("--models is required")

    try:
        robots = [int(x) for x in args.sweep.split(",") if x.strip()] if args.sweep else None
    except ValueError:
        p.error(f"--sweep: expected comma-separated robot counts, got {args.sweep!r}")
    models = parse_models(args.models)
    problem = bad_arguments(args, robots) or unknown_models(models, args.size)
    if problem:
        p.error(problem)  # before any model is built
    engines = parse_engines(args.engines, args.max_batch)
    deadlines = parse_deadlines(args.deadline)
    undated = [n for n, a in models.items() if not {n, a} & deadlines.keys() and a not in PAPER_DEADLINES_MS]
    if undated:  # before any model is built: served_models would refuse it only after the first model's run
        p.error(f"no deadline for {', '.join(undated)}: the paper has deadlines for {', '.join(PAPER_DEADLINES_MS)}; "
                "give one with --deadline name=ms")
    labels = [e.label for e in engines]
    baseline = args.baseline or ("monolithic" if "monolithic" in labels else None)
    if baseline is not None and baseline not in labels:
        raise SystemExit(f"--baseline {baseline!r} is not one of the engines {labels}")
    sim = SimConfig(epochs=args.epochs, duration_s=args.duration, drain_s=args.drain, seed=args.seed,
                    network=args.network)
    # What the search really does, as recorded: a sweep measures every point with all epochs (docs/capacity.md),
    # and screening with as many epochs as a full point is no screening.
    early_stop = robots is None and not args.no_early_stop
    screen_epochs = args.screen_epochs if robots is None and 0 < args.screen_epochs < args.epochs else None

    settings = {
        "target": args.target, "hz": args.hz, "epochs": args.epochs, "duration_s": args.duration,
        "drain_s": args.drain, "network": args.network, "max_batch": args.max_batch, "size": args.size,
        "device": args.device, "seed": args.seed, "mode": "sweep" if robots else "search",
        "sweep": robots, "screen_epochs": screen_epochs, "start": args.start,
        "max_robots": args.max_robots, "early_stop": early_stop,
        "reuse_engine": not args.no_reuse, "baseline": baseline,
        "models": models, "engines": {e.label: {"kind": e.kind, **e.overrides} for e in engines},
    }
    report = Report(args.out, settings, meta(args.device), args.merge)

    for name, arch in models.items():
        served = served_models({name: arch}, args.size, args.device, args.seed, deadlines)
        report.doc["deadlines_ms"][name] = served[name].slo_s * 1e3
        report.doc.setdefault("overlap_bound", {})[name] = overlap_bound(served[name].model, args.max_batch,
                                                                         args.device)
        hosts = {e.label: EngineHost(engine_factory(e.kind, served, args.device, **e.overrides),
                                     reuse=not args.no_reuse, label=e.label) for e in engines}
        try:
            results = compare_capacity(hosts, name, args.hz, sim, args.target, robots, args.start, args.max_robots,
                                       early_stop=early_stop, progress=not args.quiet,
                                       on_point=lambda engine, pt, m=name: report.point(m, engine, pt),
                                       screen_epochs=screen_epochs)
        finally:
            for h in hosts.values():
                h.close()
            del served
        report.model_done(name, results, baseline)
        caps = ", ".join(f"{e} {'>= ' if r.capped else ''}{r.capacity}" for e, r in results.items())
        late = sorted({f"{e} {p.robots}" for e, r in results.items() for p in r.points if not p.lag_ok})
        if late:
            print(f"{name}: warning: the harness sent late (p99 lag over {100 * LAG_LIMIT:.0f}% of the deadline) at "
                  f"{', '.join(late)}: those points measured the host too (docs/capacity.md, Send times)", flush=True)
        bound = report.doc["overlap_bound"][name]
        print(f"{name}: capacity at {100 * args.target:.0f}% SLO attainment: {caps}; overlap bound "
              f"{bound['bound']:.2f}x (VLM {bound['vlm_ms']:.2f} ms, action {bound['action_ms']:.2f} ms at batch "
              f"{bound['batch']})", flush=True)

    if args.out:
        print(f"wrote {args.out}")
    if args.plot and plot(report.doc, args.plot):
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
