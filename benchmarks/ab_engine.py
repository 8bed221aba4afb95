"""A change against the commit before it, in one call: ms per step of the status table's settings.

    python benchmarks/ab_engine.py --root OLD_CHECKOUT --device cuda --out old.json
    python benchmarks/ab_engine.py --root . --device cuda --out new.json
    python benchmarks/ab_engine.py --compare old.json new.json

Each run imports the engine and benchmarks.scenes of ``--root`` (so a second checkout of an older
commit measures itself, with the SolverConfig it had: flat knobs before engine.Tuning), builds
every scene at ``--worlds`` worlds and times each setting of ROWS through engine.pack and
engine.Stepper: CUDA graphs of 10 steps, the median of the chunks after two (compile, capture).
"maximal" and "tree" force the coordinates ("tree": every shape in one collision group, so that
shapes touch the ground only, as the tree plan models them), "default" is what each commit does
unasked. A checkout without engine.pack (before commit a7a4708) is refused: the ab_engine.py of
commit 34ad379 measures those with the API they had.
--walker-study also times one generation of studies/walker.toml's evaluation (4096 designs by
default): designs per second, build, pack and simulation included. --compare prints the ratios.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import pathlib
import sys
import time

NO_PROJECTION = dict(position_iterations=0, projection_velocity_update=False, baumgarte=0.5)
REDUCED = dict(position_iterations=2)
FEET = dict(contact_capacity=8)
# scene -> (label, coordinates, config, pack options): the status table's rows at the largest batch
ROWS = {
    "fourbar": [("default", None, {}, {}), ("maximal", "maximal", {}, {}),
                ("reduced coordinates", "tree", {}, {})],
    "mixed": [("default", None, {}, {}), ("maximal", "maximal", {}, {})],
    "drlegs_hanging": [("default", None, {}, {}), ("maximal", "maximal", {}, {}),
                       ("no projection (Baumgarte 0.5)", "maximal", NO_PROJECTION, {}),
                       ("reduced coordinates", "tree", REDUCED, {}),
                       ("reduced coordinates, 1 projection", "tree", dict(position_iterations=1), {}),
                       ("reduced coordinates, no projection (Baumgarte 0.5)", "tree",
                        dict(position_iterations=0, baumgarte=0.5), {})],
    "drlegs_standing": [("default", None, {}, {}), ("maximal", "maximal", {}, {}),
                        ("1 projection iteration", "maximal", dict(position_iterations=1), {}),
                        ("projection on the PADMM pattern", "maximal", dict(sparse_projection_pattern="never"), {}),
                        ("projection on its own pattern", "maximal", dict(sparse_projection_pattern="always"), {})],
    "drlegs_standing_newton": [("default", None, {}, {}), ("maximal", "maximal", {}, {}),
                               ("reduced coordinates", "tree", REDUCED, {}),
                               ("reduced coordinates, 8 contacts", "tree", REDUCED, FEET),
                               ("reduced coordinates, 8 contacts, no projection (Baumgarte 0.5)", "tree",
                                dict(position_iterations=0, baumgarte=0.5), FEET),
                               ("reduced coordinates, 8 contacts, skip floors 3e-7 m, 3e-6 rad", "tree",
                                dict(position_iterations=2, projection_skip_floor=3e-7,
                                     projection_skip_floor_angular=3e-6), FEET)],
    "walker": [("default", None, {}, {}), ("maximal", "maximal", {}, {})],
    "walker_default": [("default", None, {}, {}), ("maximal", "maximal", {}, {})],
}


def _commit(root: str) -> str:
    """The checkout's commit (no machine path in a result file), or 'unknown'."""
    import subprocess

    try:
        return subprocess.run(["git", "-C", root, "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown (not a git checkout)"


def _planned(engine) -> bool:
    """Whether the commit has engine.pack() (before it, engine.pack was the maximal packer's module)."""
    return callable(getattr(engine, "pack", None))


def _ground_only(spec):
    """``spec`` with every shape in one collision group: ground contacts only, what the tree plan
    models (it refuses worlds whose shapes may touch each other)."""
    if not spec.shapes:
        return spec
    return dataclasses.replace(spec, shapes=[dataclasses.replace(s, collision_group=1) for s in spec.shapes])


def _config(engine, values: dict):
    """A SolverConfig of ``values`` in the API of the commit being measured (flat fields before the
    public/tuning split, SolverConfig(public).tuned(rest) after it)."""
    fields = {f.name for f in dataclasses.fields(engine.SolverConfig)}
    public = {k: v for k, v in values.items() if k in fields}
    config = engine.SolverConfig(**public)
    rest = {k: v for k, v in values.items() if k not in fields}
    return config.tuned(**rest) if rest else config


def _stepper(engine, batch, coords, values, pack, device, dt):
    """(stepper, plan text) of one setting."""
    config = _config(engine, values)
    if coords == "tree":
        batch = [_ground_only(spec) for spec in batch]
    model = engine.pack(batch, device, config=config, dt=dt, coordinates=coords, **pack)
    return engine.Stepper(model, model.state(), chunk=10), str(model.plan).splitlines()[0]


def time_setting(engine, wp, batch, coords, values, pack, device, dt, steps) -> dict:
    """Median ms per step over the chunks after the first two."""
    t0 = time.perf_counter()
    stepper, plan = _stepper(engine, batch, coords, values, pack, device, dt)
    pack_s = time.perf_counter() - t0
    times = []
    for _ in range(2 + max(3, steps // 10)):
        wp.synchronize_device(device)
        t = time.perf_counter()
        stepper.advance()
        wp.synchronize_device(device)
        times.append((time.perf_counter() - t) / 10)
    ms = sorted(times[2:])[len(times[2:]) // 2] * 1e3
    return {"ms_per_step": ms, "first_chunks_s": [round(10 * t, 3) for t in times[:2]], "pack_s": pack_s, "plan": plan}


def walker_study(engine, device: str, designs: int) -> dict:
    """One generation of studies/walker.toml's evaluation: designs per second (two generations, the
    second timed: the first compiles)."""
    import numpy as np
    from morphopt.evaluate import evaluate_dynamic
    from morphopt.families import load_family

    family = load_family("walker")
    rng = np.random.default_rng(0)
    params = []
    while len(params) < designs:
        for p in family.space.sample(rng, designs):
            try:
                params.append(family.space.validate({**p, "legs_per_side": 3}))
            except ValueError:
                continue
    params = params[:designs]
    values = dict(tolerance=1e-4, relative_tolerance=1e-3, max_iterations=30, rho_update_interval=8)
    kwargs = dict(duration=2.0, dt=0.005, device=device)
    config = _config(engine, values)
    out = {}
    for run in ("compile", "timed"):
        t = time.perf_counter()
        evaluation = evaluate_dynamic(family, params, config=config, **kwargs)
        seconds = time.perf_counter() - t
        out[run] = {"seconds": seconds, "designs_per_s": len(params) / seconds,
                    "timings": {k: round(v, 3) for k, v in evaluation.timings.items()},
                    "feasible": int(np.sum(evaluation.feasible))}
    return out


def compare(old_file: str, new_file: str) -> None:
    old, new = (json.loads(pathlib.Path(f).read_text()) for f in (old_file, new_file))
    by = {(r["scene"], r["label"]): r for r in old["rows"]}
    print(f"{'scene':24} {'setting':62} {'old ms':>8} {'new ms':>8} {'new/old':>8}")
    for r in new["rows"]:
        o = by.get((r["scene"], r["label"]))
        if o is None or "ms_per_step" not in o or "ms_per_step" not in r:
            continue
        print(f"{r['scene']:24} {r['label'][:62]:62} {o['ms_per_step']:8.3f} {r['ms_per_step']:8.3f} "
              f"{r['ms_per_step'] / o['ms_per_step']:8.3f}")
    if "walker_study" in old and "walker_study" in new:
        a, b = old["walker_study"]["timed"], new["walker_study"]["timed"]
        print(f"walker study designs/s: old {a['designs_per_s']:.0f}, new {b['designs_per_s']:.0f}, "
              f"new/old {b['designs_per_s'] / a['designs_per_s']:.3f}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", default=".", help="the checkout to measure")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--scenes", nargs="+", default=list(ROWS))
    parser.add_argument("--assets", default=None, help="folder holding disneyresearch/dr_legs")
    parser.add_argument("--walker-study", type=int, default=0, metavar="DESIGNS")
    parser.add_argument("--out", default=None)
    parser.add_argument("--compare", nargs=2, metavar=("OLD", "NEW"))
    args = parser.parse_args(argv)
    if args.compare:
        compare(*args.compare)
        return
    root = str(pathlib.Path(args.root).resolve())
    sys.path = [root] + [p for p in sys.path if pathlib.Path(p or ".").resolve() != pathlib.Path(__file__).parent]
    import warp as wp

    import engine
    from benchmarks.scenes import SCENES_DECLARED

    if not _planned(engine):
        parser.error(f"--root {root}: this checkout has no engine.pack (before commit a7a4708); measure it with "
                     f"the ab_engine.py of commit 34ad379")
    wp.config.quiet = True
    result = {"root": _commit(root), "device": wp.get_device(args.device).name, "worlds": args.worlds, "rows": []}
    for scene in args.scenes:
        declared = SCENES_DECLARED[scene]
        try:
            specs = declared.build(args.assets).specs
        except FileNotFoundError as exc:
            print(json.dumps({"scene": scene, "skipped": str(exc)}), flush=True)
            continue
        batch = [specs[w % len(specs)] for w in range(args.worlds)]
        for label, coords, values, pack in ROWS[scene]:
            row = {"scene": scene, "label": label}
            try:
                row.update(time_setting(engine, wp, batch, coords, values, pack, args.device, declared.dt,
                                        declared.throughput_steps))
            except Exception as exc:  # noqa: BLE001 - a setting the commit cannot run is reported, not fatal
                row["error"] = f"{type(exc).__name__}: {exc}"[:300]
            result["rows"].append(row)
            print(json.dumps(row), flush=True)
            if args.out:  # kept after every row: a run cut short still leaves what it measured
                pathlib.Path(args.out).write_text(json.dumps(result, indent=1))
            gc.collect()
    if args.walker_study:
        result["walker_study"] = walker_study(engine, args.device, args.walker_study)
        print(json.dumps(result["walker_study"]), flush=True)
    if args.out:
        pathlib.Path(args.out).write_text(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
