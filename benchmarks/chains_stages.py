"""Where engine.reduced.chains' fused step spends a world's time: the clock at the end of each stage.

    python -m benchmarks.chains_stages --device cuda --scenes drlegs_standing_newton drlegs_hanging --worlds 4096
        [--variant LABEL] [--steps 20] [--warmup 30] [--assets DIR] [--out FILE]

Each scene of benchmarks.scenes (its dt) in reduced coordinates (engine.pack's TREE plan, forced; the
ChainModel it holds, ``.inner``, is the one stepped with clocks), with the settings and packing of its
variant ``--variant`` (default "reduced coordinates"; "reduced coordinates, 8 contacts" keeps DR Legs
standing's feet's 8 contacts): after ``--warmup`` steps, ``--steps`` steps of the step kernel compiled
with a clock reading at the end of each stage (engine.reduced.chain_stages.STAGES, ChainModel.step(stages=True);
the same step otherwise). Per stage: the cycles from its start to its end of each world's block,
the mean over the worlds that ran it, then over the steps, and its share of the step. On a GPU
those are SM cycles of one block and include the issue slots it waits for while other blocks run
on its SM, so they say where a world's time goes at that occupancy (a stage's share of the kernel's
time), not what the stage would take alone; on the CPU they are the processor's cycles. Prints one
JSON line per scene and writes them to --out, with a CSV (one row per scene and stage) and a PNG
(a bar per stage) beside it.
"""

import argparse
import csv
import json
import os
import pathlib
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np
import warp as wp


def stage_cycles(specs, worlds: int, dt: float, device: str, config=None, pack: dict | None = None,
                 steps: int = 20, warmup: int = 30) -> dict:
    """Mean cycles per stage (STAGES order, stages no world ran left out) over
    ``steps`` steps after ``warmup``, ``worlds`` worlds cycling through ``specs`` packed by
    engine.pack in the TREE plan (``pack``: its other options; the ChainModel it holds is stepped
    with the clocks), and the PADMM iterations those steps took (mean over worlds and steps)."""
    import engine
    from engine.reduced.chain_stages import STAGES

    batch = [specs[w % len(specs)] for w in range(worlds)]
    model = engine.pack(batch, device, config=config, dt=dt, coordinates="tree", **(pack or {})).inner
    state = model.state()
    for _ in range(warmup):
        model.step(state)
    totals, counts, iterations = {}, {}, []
    for _ in range(steps):
        model.step(state, stages=True)
        for name, cycles in model.stage_cycles().items():
            totals[name] = totals.get(name, 0.0) + cycles
            counts[name] = counts.get(name, 0) + 1
        iterations.append(float(model.work.iterations.numpy().mean()))
    stages = {name: totals[name] / counts[name] for name in STAGES if name in totals}
    return {"stages": stages, "step_cycles": sum(stages.values()), "padmm_iterations_mean": float(np.mean(iterations)),
            "diverged_worlds": int(model.diverged.sum())}


def variant_of(declared, label: str) -> dict:
    """The variant of ``declared`` (a benchmarks.scenes.Declared) with this label, in reduced coordinates
    (coordinates "tree")."""
    for variant in declared.variants:
        if variant["label"] == label and variant.get("coordinates") == "tree":
            return variant
    labels = [v["label"] for v in declared.variants if v.get("coordinates") == "tree"]
    raise ValueError(f"chains_stages: no reduced-coordinate variant {label!r} (this scene has {labels})")


def plot(rows: list, path: pathlib.Path) -> None:
    """A horizontal bar per stage and scene: its share of the step."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from engine.reduced.chain_stages import STAGES

    names = [s for s in STAGES if any(s in r["stages"] for r in rows)]
    fig, ax = plt.subplots(figsize=(8.0, 0.22 * len(names) * max(1, len(rows)) + 1.5))
    height = 0.8 / max(1, len(rows))
    for k, row in enumerate(rows):
        shares = [row["stages"].get(s, 0.0) / row["step_cycles"] for s in names]
        ax.barh(np.arange(len(names)) + k * height, shares, height=height,
                label=f"{row['scene']} ({row['variant']}, {row['num_worlds']} worlds)")
    ax.set_yticks(np.arange(len(names)) + 0.4 - height / 2)
    ax.set_yticklabels(names, fontsize=8)
    ax.invert_yaxis()
    ax.set_xlabel("share of a world's step (clock at each stage's end)")
    ax.set_title(f"engine.reduced.chains' step by stage, {rows[0]['device_name']}", fontsize=9)
    ax.legend(fontsize=7)
    ax.grid(True, axis="x", alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    from benchmarks.run import write_rows
    from benchmarks.scenes import SCENES_DECLARED, ground_contacts_only
    from engine import SolverConfig

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--scenes", nargs="+", default=["drlegs_hanging"], choices=sorted(SCENES_DECLARED))
    parser.add_argument("--variant", default="reduced coordinates",
                        help="the scene's reduced-coordinate variant (its settings and packing)")
    parser.add_argument("--worlds", type=int, default=4096)
    parser.add_argument("--steps", type=int, default=20, help="steps timed by stage")
    parser.add_argument("--warmup", type=int, default=30, help="steps before them (compile, settle)")
    parser.add_argument("--assets", default=None, help="folder holding the DR Legs asset")
    parser.add_argument("--out", default=None, help="JSON file (CSV and PNG beside it)")
    args = parser.parse_args(argv)
    if args.worlds < 1 or args.steps < 1 or args.warmup < 0:
        parser.error("--worlds and --steps must be >= 1, --warmup >= 0")
    wp.config.quiet = True
    device = wp.get_device(args.device)
    rows = []
    for name in args.scenes:
        declared = SCENES_DECLARED[name]
        try:
            variant = variant_of(declared, args.variant)
        except ValueError as exc:
            parser.error(f"{name}: {exc}")
        scene = declared.build(args.assets)
        specs = [ground_contacts_only(spec) for spec in scene.specs] if variant.get("ground_only") else scene.specs
        row = {"scene": name, "variant": args.variant, "device": str(device), "device_name": device.name,
               "num_worlds": args.worlds, "dt": declared.dt, "steps": args.steps, "settings": variant["config"],
               "pack": variant.get("pack", {}),
               **stage_cycles(specs, args.worlds, declared.dt, args.device,
                              SolverConfig(**variant["config"]), variant.get("pack"), args.steps, args.warmup)}
        print(json.dumps(row), flush=True)
        rows.append(row)
    if args.out:
        out = pathlib.Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        write_rows(out, args.device, "benchmarks.chains_stages", argv, rows)
        with open(out.with_suffix(".csv"), "w", newline="") as f:
            writer = csv.writer(f)
            writer.writerow(["scene", "variant", "num_worlds", "stage", "cycles", "share"])
            for row in rows:
                for stage, cycles in row["stages"].items():
                    writer.writerow([row["scene"], row["variant"], row["num_worlds"], stage, round(cycles, 1),
                                     round(cycles / row["step_cycles"], 4)])
        plot(rows, out.with_suffix(".png"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
