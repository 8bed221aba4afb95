"""The `morphopt` command line: nested subcommands.

    morphopt study run SPEC [--device D] [--worlds N] [--generations G] [--seed S] [--fresh] [--steal]
    morphopt study resume SPEC [--generations G] [--device D] [--steal] [--trust-checkpoint]
    morphopt study show SPEC [--top K]
    morphopt study plot SPEC [--out PNG]
    morphopt study export SPEC --optuna-storage URL
    morphopt export SPEC [--best K] --format usd|urdf|mjcf|svg|dxf [--out DIR] [--motion SECONDS]
    morphopt demo fourbar [--worlds N] [--seconds S] [--dt DT] [--device cpu|cuda]
    morphopt families [show NAME]

``--verbose`` (before or after the command) shows Warp's init banner, module loads and CUDA driver
warning on stderr; without it stdout holds only the command's results.

Bad input (a missing or malformed study file, an unknown key or family, a bad argument, a device
that is not there) ends the command with exit status 2 and one line on stderr naming the item and
what was expected, never a traceback; a failed study command leaves its stored results as they were.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys

from morphopt import __version__

DEMO_SCENES = {  # engine.scenes: passive planar linkages of slender bars under gravity
    "pendulum": "one bar hanging from a pivot",
    "fourbar": "a four-bar linkage (one closed loop)",
    "sixbar": "a Watt II six-bar (two closed loops)",
    "chain": "an open chain of 10 bars",
    "mixed": "the four above, one per world, in one batch",
}
EXPORT_FORMATS = {  # morphopt.formats
    "usd": "OpenUSD with UsdPhysics bodies and joints",
    "urdf": "URDF of the joints' spanning tree, the loop closures in a <morphopt> extension element",
    "mjcf": "MuJoCo XML, a body tree whose loops are closed by equality constraints",
    "svg": "fabrication drawing of the links, 1:1 in mm",
    "dxf": "the same drawing as DXF",
}


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors: "morphopt <command>: error: <argument>: <what was expected>", status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see '{self.prog} --help')\n")


def _positive(kind):
    def parse(text):
        try:
            value = kind(text)
        except ValueError as exc:
            article = "an" if kind.__name__[0] in "aeiou" else "a"
            raise argparse.ArgumentTypeError(f"expected {article} {kind.__name__}, got {text!r}") from exc
        if not value > 0:
            raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
        return value
    return parse


def _demo(args) -> int:
    from engine.testspeed import run
    from morphopt.warp_setup import Kernels, announce_compile

    announce_compile(Kernels.DYNAMIC, args.device)
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


def _study_spec(args):
    """The study file with the overrides of the command line; every command but `run` first applies
    the ones the stored study was run with (morphopt.study.stored_spec)."""
    from morphopt.study_spec import load_study_spec

    spec = load_study_spec(args.spec)  # checks the file before any heavy import (Warp, the engine, optimizers)
    from morphopt.warp_setup import quiet_warp

    quiet_warp()
    if getattr(args, "study_command", None) != "run":
        from morphopt.study import stored_spec

        command = getattr(args, "study_command", None)
        spec = stored_spec(spec, say=command == "resume" and getattr(args, "generations", None) is None)
    overrides = {k: getattr(args, k, None)
                 for k in ("device", "worlds", "generations", "seed", "cluster", "workers", "gpus_per_worker")}
    return spec.with_overrides(**overrides)


def _study_run(args) -> int:
    spec = _study_spec(args)
    from morphopt.study import run_study

    result = run_study(spec, resume=args.study_command == "resume", fresh=getattr(args, "fresh", False),
                       steal=args.steal, trust_checkpoint=getattr(args, "trust_checkpoint", False))
    print(f"study '{spec.name}': {result.evaluations} designs in {result.seconds:.1f} s "
          f"({result.evaluations / max(result.seconds, 1e-9):,.0f} designs/s; sampling and storage "
          f"{100 * result.overhead:.1f} % of it), results in {spec.storage_url}")
    if result.stages:
        print("time by stage: " + ", ".join(f"{stage} {spent:.3g} s" for stage, spent in result.stages.items()))
    if result.best_params is None:
        print("no feasible design found")
        return 1
    print(f"best {spec.metric} = {result.best_value:.6g} ({spec.direction})")
    for name, value in result.best_params.items():
        print(f"  {name:>12} = {value:.6g}" if isinstance(value, float) else f"  {name:>12} = {value}")
    return 0


def _stored_designs(args):
    """The spec and its stored designs (a DataFrame), or (spec, None) after saying there are none."""
    from morphopt.storage import read_designs

    spec = _study_spec(args)
    frame = read_designs(spec.storage_url, spec.name)
    if frame.empty:
        print(f"study '{spec.name}' has no stored designs in {spec.storage_url}")
        return spec, None
    return spec, frame


def _study_show(args) -> int:
    from morphopt.families import load_family
    from morphopt.report import study_report

    spec, frame = _stored_designs(args)
    if frame is None:
        return 1
    print(study_report(frame, spec, load_family(spec.family).space, args.top))
    from morphopt.storage import read_workers

    workers = read_workers(spec.storage_url, spec.name)
    if len(workers):
        print("workers (Ray cluster):")
        for worker, rows in workers.groupby("worker"):
            designs, seconds = int(rows.designs.sum()), float(rows.seconds.sum())
            replaced = int(rows.replaced.sum())
            print(f"  worker {worker}: {designs} designs in {len(rows)} generations, "
                  f"{designs / max(seconds, 1e-9):,.1f} designs/s, {int(rows.failures.sum())} failed"
                  + (f", replaced {replaced}x" if replaced else ""))
    return 0


def _study_plot(args) -> int:
    from morphopt.families import load_family
    from morphopt.plots import plot_study
    spec, frame = _stored_designs(args)
    if frame is None:
        return 1
    out = args.out or str(spec.path.with_suffix(".png"))
    print(plot_study(frame, spec, load_family(spec.family), out))
    return 0


def _study_export(args) -> int:
    from morphopt.families import load_family
    from morphopt.storage import export_to_optuna

    spec, frame = _stored_designs(args)
    if frame is None:
        return 1
    space = spec.design_space(load_family(spec.family))
    written, present = export_to_optuna(frame, study_name=spec.name, space=space, direction=spec.direction,
                                        storage=args.optuna_storage)
    already = f"; {present} designs were there already" if present else ""
    print(f"exported {written} trials of '{spec.name}' to {args.optuna_storage}{already} "
          f"(optuna-dashboard {args.optuna_storage})")
    return 0


def _export(args) -> int:
    import math

    from morphopt.formats import MOTION_FORMATS

    if args.motion is not None and args.format not in MOTION_FORMATS:  # refused before any work
        raise ValueError(f"--motion: format '{args.format}' cannot carry a motion; only "
                         f"{', '.join(MOTION_FORMATS)} has time samples")
    from morphopt.build import crank_speed_of
    from morphopt.families import load_family
    from morphopt.formats import export_design

    spec, frame = _stored_designs(args)
    if frame is None:
        return 1
    feasible = frame[frame["failure"] == ""]
    if feasible.empty:
        print(f"study '{spec.name}' has no feasible design to export")
        return 1
    family = load_family(spec.family)
    names = family.space.names
    best = feasible.sort_values("value", ascending=spec.direction == "minimize").head(args.best)
    out = pathlib.Path(args.out) if args.out else pathlib.Path(args.spec).resolve().parent / f"{spec.name}_export"
    settings = {"mode": spec.mode, "dt": spec.dt, "duration": spec.duration,
                "crank_speed": crank_speed_of(family, spec.crank_speed), "solver": dict(spec.solver)}
    for rank, row in enumerate(best.itertuples(index=False), start=1):
        record = row._asdict()
        params = {k: _plain(record[k]) for k in (*names, *spec.fixed) if k in record}
        metrics = {k[len("metric_"):]: _plain(v) for k, v in record.items()
                   if k.startswith("metric_") and isinstance(v, (int, float)) and math.isfinite(v)}
        name = f"{spec.name}_rank{rank}_g{record['generation']}_m{record['member']}"
        metadata = {"study": spec.name, "family": spec.family, "rank": rank, "generation": int(record["generation"]),
                    "member": int(record["member"]), "objective": {spec.metric: float(record["value"])},
                    "params": params, "metrics": metrics, "simulation": settings}
        path = export_design(family, params, args.format, out, name=name, metadata=metadata,
                             crank_speed=spec.crank_speed, dt=spec.dt, config=spec.solver_config(),
                             motion_seconds=args.motion or 0.0)
        print(f"{path}  ({spec.metric} {record['value']:.6g})")
    return 0


def _families(args) -> int:
    from morphopt.catalog import family_sheet, family_table

    print(family_sheet(args.name) if args.families_command == "show" else family_table())
    return 0


def _plain(value):
    """A pandas/NumPy scalar as a plain Python value (for JSON metadata and the families)."""
    return value.item() if hasattr(value, "item") else value


def _choices(options: dict) -> str:
    return "; ".join(f"{name}: {text}" for name, text in options.items())


def build_parser() -> argparse.ArgumentParser:
    """The ``morphopt`` argument parser: ``study run|resume|show|plot|export``, ``export``, ``demo``."""
    verbose = argparse.ArgumentParser(add_help=False)  # --verbose after any command as well
    verbose.add_argument("--verbose", action="store_true", default=argparse.SUPPRESS,
                         help="show Warp's messages (init banner, module loads, CUDA driver warning) on stderr")
    parser = _Parser(prog="morphopt", description="Closed-chain mechanism design optimization.")
    parser.add_argument("--version", action="version", version=f"morphopt {__version__}")
    parser.add_argument("--verbose", action="store_true", default=False,
                        help="show Warp's messages (init banner, module loads, CUDA driver warning) on stderr")
    commands = parser.add_subparsers(dest="command", required=True)
    study = commands.add_parser("study", help="run, resume, show, plot or export a design study (TOML spec)",
                                description="Run, resume, show, plot or export a design study (TOML spec).")
    study_commands = study.add_subparsers(dest="study_command", required=True)
    for name, handler, text in (("run", _study_run, "run a study from scratch"),
                                ("resume", _study_run, "continue an interrupted study"),
                                ("show", _study_show, "best designs as a table, and progress"),
                                ("plot", _study_plot, "convergence and the best design, as a PNG"),
                                ("export", _study_export, "copy the designs into an Optuna storage")):
        sub = study_commands.add_parser(name, help=text, parents=[verbose])
        sub.add_argument("spec", help="study TOML file")
        if name == "run":
            sub.add_argument("--device", help="Warp device: cpu, cuda, cuda:N")
            sub.add_argument("--worlds", type=_positive(int), help="designs per generation (worlds per batch)")
            sub.add_argument("--generations", type=_positive(int), help="number of generations")
            sub.add_argument("--seed", type=int, help="random seed")
            sub.add_argument("--fresh", action="store_true",
                             help="start over on a study that has results (they are kept under a new name)")
        if name == "resume":
            sub.add_argument("--generations", type=_positive(int),
                             help="total generations (more than stored: extends the study)")
            sub.add_argument("--device", help="Warp device to continue on: cpu, cuda, cuda:N")
            sub.add_argument("--trust-checkpoint", action="store_true",
                             help="a study stored by an earlier morphopt (a pickled checkpoint, never unpickled): "
                                  "rebuild its optimizer from the stored designs")
        if name in ("run", "resume"):
            sub.add_argument("--cluster", metavar="ADDRESS",
                             help="evaluate on a Ray cluster: 'local' (started here), 'auto' (the one this machine "
                                  "belongs to) or host:port (pip install \"morphopt[cluster]\")")
            sub.add_argument("--workers", type=_positive(int),
                             help="Ray workers (default: one per GPU of a CUDA study, else one per CPU core)")
            sub.add_argument("--gpus-per-worker", type=float, metavar="SHARE",
                             help="a CUDA study's share of a GPU per worker, 0.0001 to 1 (default 1; 0.5: two workers "
                                  "on each GPU, which a worker's host side can leave half idle)")
            sub.add_argument("--steal", action="store_true",
                             help="take the study over from a writer that is gone (its lease is not yet stale)")
        if name == "show":
            sub.add_argument("--top", type=_positive(int), default=10, help="rows to show (default 10)")
        if name == "plot":
            sub.add_argument("--out", help="PNG path (default: beside the spec)")
        if name == "export":
            sub.add_argument("--optuna-storage", required=True, help="Optuna storage URL, e.g. sqlite:///optuna.db")
        sub.set_defaults(handler=handler)
    export = commands.add_parser("export", help="write the best designs of a study as USD, URDF, MJCF, SVG or DXF",
                                 parents=[verbose])
    export.add_argument("spec", help="study TOML file")
    export.add_argument("--best", type=_positive(int), default=1, help="how many of the best designs (default 1)")
    export.add_argument("--format", required=True, choices=tuple(EXPORT_FORMATS),
                        help="file format: " + _choices(EXPORT_FORMATS))
    export.add_argument("--out", help="output folder (default: <study name>_export beside the spec)")
    export.add_argument("--motion", type=_positive(float),
                        help="USD only (other formats refuse it): simulate this many seconds (the study's dt, "
                             "crank_speed and [solver] settings) and add the motion as time samples")
    export.set_defaults(handler=_export)
    demo = commands.add_parser("demo", help="simulate a reference mechanism and print what was measured",
                               parents=[verbose])
    demo.add_argument("scene", choices=tuple(DEMO_SCENES), help="the mechanism: " + _choices(DEMO_SCENES))
    demo.add_argument("--worlds", type=_positive(int), default=16, help="number of worlds (default 16)")
    demo.add_argument("--seconds", type=_positive(float), default=2.0, help="simulated time [s] (default 2)")
    demo.add_argument("--dt", type=_positive(float), default=1e-3, help="time step [s] (default 0.001)")
    demo.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:N (default cpu)")
    demo.add_argument("--json", action="store_true", help="print one JSON object")
    demo.set_defaults(handler=_demo)
    families = commands.add_parser("families", help="list the design families, or show one's parameters and metrics",
                                   parents=[verbose])
    families_commands = families.add_subparsers(dest="families_command")
    show = families_commands.add_parser("show", parents=[verbose],
                                        help="a family's parameters (range, default, unit, meaning) and metrics")
    show.add_argument("name", help="family name (as listed by 'morphopt families') or path to a .py file")
    families.set_defaults(handler=_families)
    return parser


def _check_demo_device(device: str) -> None:
    import warp as wp

    if device.startswith("cuda") and not wp.is_cuda_available():
        raise ValueError(f"--device '{device}' requested but no CUDA device is available")
    try:
        wp.get_device(device)
    except (RuntimeError, ValueError) as exc:
        raise ValueError(f"--device '{device}': expected cpu, cuda or cuda:N of this machine ({exc})") from exc


def main(argv=None) -> int:
    """Run one command; returns its exit status (argparse exits with 2 itself on a bad argument)."""
    args = build_parser().parse_args(argv)
    command = f"study {args.study_command}" if args.command == "study" else args.command
    if args.command == "families" and args.families_command:
        command = f"families {args.families_command}"
    from morphopt.warp_setup import quiet_warp, set_verbose

    set_verbose(args.verbose)
    try:
        if args.command == "demo":
            quiet_warp()
            _check_demo_device(args.device)
        return args.handler(args)
    except (ValueError, OSError) as exc:  # bad input: one line naming it, no traceback
        message = str(exc).replace("\n", " ")
        print(f"morphopt {command}: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
