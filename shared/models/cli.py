"""``robion models [--json] [--size SIZE]``: the registered architectures at their full size (or SIZE).

A user's own architectures are listed when their modules are named in ROBION_IMPORTS
(comma-separated); a cluster config names them under ``imports``.

Models are built on the meta device, so listing costs no memory. The ``toy`` test
architecture is left out; every other registered architecture (built-in or a user's)
is listed. One without the size asked for is named on stderr; one whose constructor fails
on the meta device too, and the exit status is then 1.
"""

from __future__ import annotations

import argparse
import json
import sys

from shared.models.registry import architectures, build_meta

HIDDEN = {"toy"}


def describe(size: str = "full", notes: list[str] | None = None,
             errors: list[str] | None = None) -> dict[str, dict[str, int]]:
    """Each listed architecture at ``size``. An architecture without that size is left out (and named in
    ``notes``); with ``errors``, one that cannot be built on the meta device is named there and left out
    instead of stopping the listing."""
    out = {}
    for name, cls in sorted(architectures().items()):
        if name in HIDDEN:
            continue
        sizes = getattr(cls, "CONFIGS", {})
        if size not in sizes:
            if notes is not None:
                notes.append(f"{name}: no size {size!r} (sizes: {', '.join(sorted(sizes)) or 'none'}); "
                                f"list it with --size")
            continue
        try:
            m = build_meta(name, size)
            counts = m.stage_parameters()
            out[name] = {"vlm_params": counts["vlm_params"], "action_params": counts["action_params"],
                         "cameras": len(m.io.cameras), "horizon": m.io.horizon, "action_dim": m.io.action_dim,
                         "steps": m.io.steps}
        except Exception as exc:  # a user's constructor: one that cannot run on the meta device hides no other
            if errors is None:
                raise
            errors.append(f"{name}: cannot be described ({type(exc).__name__}: {exc})")
    return out


def count(n: int) -> str:
    """A parameter count in the unit that keeps its digits (a 2 k-parameter stage is not "0.0M")."""
    for unit, scale in (("B", 1e9), ("M", 1e6), ("K", 1e3)):
        if n >= scale:
            return f"{n / scale:.3g}{unit}" if n < 100 * scale else f"{n / scale:.0f}{unit}"
    return str(n)


def main(argv: list[str] | None = None) -> int:
    """Exit status 0, 1 when an architecture could not be described (the others are still listed), or 2 when
    no architecture has the size asked for."""
    ap = argparse.ArgumentParser(prog="robion models", description="List the servable VLA architectures.")
    ap.add_argument("--json", action="store_true", help="machine-readable output")
    ap.add_argument("--size", default="full", help="config size to describe (default: full)")
    args = ap.parse_args(argv)
    notes: list[str] = []
    errors: list[str] = []
    try:
        info = describe(args.size, notes, errors)
    except ImportError as exc:  # a module of the user's named in ROBION_IMPORTS
        print(f"robion models: {exc}", file=sys.stderr)
        return 2
    if not info and not errors and notes:  # a size no listed architecture has: a mistyped --size
        print(f"robion models: no architecture has the size {args.size!r}:", *notes, sep="\n  ", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print(f"{'architecture':<14} {'VLM params':>11} {'action params':>14} {'cameras':>8} {'horizon':>8} "
              f"{'action dim':>10} {'steps':>6}")
        for name, r in info.items():
            print(f"{name:<14} {count(r['vlm_params']):>11} {count(r['action_params']):>14} {r['cameras']:>8} "
                  f"{r['horizon']:>8} {r['action_dim']:>10} {r['steps']:>6}")
    for line in notes + errors:
        print(f"robion models: {line}", file=sys.stderr)
    return 1 if errors else 0


if __name__ == "__main__":
    raise SystemExit(main())
