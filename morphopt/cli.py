"""The `morphopt` command line: nested subcommands.

    morphopt demo fourbar [--worlds N] [--seconds S] [--dt DT] [--device cpu|cuda]
"""

from __future__ import annotations

import argparse
import json
import sys

from morphopt import __version__

DEMO_SCENES = ("pendulum", "fourbar", "sixbar", "chain", "mixed")


def _positive(kind):
    def parse(text):
        try:
            value = kind(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(f"expected a {kind.__name__}, got {text!r}") from exc
        if not value > 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        return value
    return parse


def _demo(args) -> int:
    import warp as wp

    from engine.testspeed import run

    wp.config.log_level = wp.LOG_WARNING
    steps = max(1, round(args.seconds / args.dt))
    result = run(args.scene, args.worlds, steps, args.dt, args.device, chunk=min(50, steps))
    if args.json:
        print(json.dumps(result))
        return 0
    print(f"morphopt demo {args.scene}: {args.worlds} worlds x {result['steps']} steps of {args.dt * 1e3:g} ms "
          f"on {result['device']} ({result['device_name']})")
    print(f"  speed             {result['world_steps_per_s']:,.0f} world-steps/s "
          f"({result['step_ms_median']:.3f} ms per step, first-step compile {result['compile_s']:.1f} s)")
    print(f"  loop closure      {result['max_constraint_violation_m']:.2e} m, "
          f"{result['max_constraint_violation_rad']:.2e} rad (max over the run)")
    print(f"  energy drift      {100 * result['energy_drift_rel']:.4f} % of the energy above equilibrium")
    print(f"  PADMM iterations  mean {result['padmm_iterations_mean']:.2f}, max {result['padmm_iterations_max']}")
    print(f"  diverged worlds   {result['diverged_worlds']}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="morphopt", description="Closed-chain mechanism design optimization.")
    parser.add_argument("--version", action="version", version=f"morphopt {__version__}")
    commands = parser.add_subparsers(dest="command", required=True)
    demo = commands.add_parser("demo", help="simulate a reference mechanism and print what was measured")
    demo.add_argument("scene", choices=DEMO_SCENES)
    demo.add_argument("--worlds", type=_positive(int), default=16, help="number of worlds (default 16)")
    demo.add_argument("--seconds", type=_positive(float), default=2.0, help="simulated time [s] (default 2)")
    demo.add_argument("--dt", type=_positive(float), default=1e-3, help="time step [s] (default 0.001)")
    demo.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:N (default cpu)")
    demo.add_argument("--json", action="store_true", help="print one JSON object")
    demo.set_defaults(handler=_demo)
    return parser


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.command == "demo" and args.device.startswith("cuda"):
        import warp as wp

        if not wp.is_cuda_available():
            print(f"morphopt demo: device '{args.device}' requested but no CUDA device is available", file=sys.stderr)
            return 2
    return args.handler(args)


if __name__ == "__main__":
    sys.exit(main())
