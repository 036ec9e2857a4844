"""``robion models [--json]``: the registered architectures at their full size.

A user's own architectures are listed when their modules are named in ROBION_IMPORTS
(comma-separated); a cluster config names them under ``imports``.

Models are built on the meta device, so listing costs no memory. The ``toy`` test
architecture is left out; every other registered architecture (built-in or a user's)
is listed.
"""

from __future__ import annotations

import argparse
import json
import sys

from shared.models.registry import architectures, build_meta

HIDDEN = {"toy"}


def describe(size: str = "full") -> dict[str, dict[str, int]]:
    out = {}
    for name, cls in sorted(architectures().items()):
        if name in HIDDEN or size not in getattr(cls, "CONFIGS", {}):
            continue
        m = build_meta(name, size)
        counts = m.stage_parameters()
        out[name] = {"vlm_params": counts["vlm_params"], "action_params": counts["action_params"],
                     "cameras": len(m.io.cameras), "horizon": m.io.horizon, "action_dim": m.io.action_dim,
                     "steps": m.io.steps}
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="robion models", description="List the servable VLA architectures.")
    ap.add_argument("--json", action="store_true", help="machine-readable output")
    ap.add_argument("--size", default="full", help="config size to describe (default: full)")
    args = ap.parse_args(argv)
    try:
        info = describe(args.size)
    except ImportError as exc:  # a module of the user's named in ROBION_IMPORTS
        print(f"robion models: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(info, indent=2))
        return 0
    print(f"{'architecture':<14} {'VLM params':>12} {'action params':>14} {'cameras':>8} {'horizon':>8} "
          f"{'action dim':>10} {'steps':>6}")
    for name, r in info.items():
        print(f"{name:<14} {r['vlm_params'] / 1e9:>11.3f}B {r['action_params'] / 1e6:>13.1f}M {r['cameras']:>8} "
              f"{r['horizon']:>8} {r['action_dim']:>10} {r['steps']:>6}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
