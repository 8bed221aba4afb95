"""The tabulated plan's two kernels against batch size: a block of lanes per world (tiled) and one
thread per world, for random walkers, so engine.reduced.tabulated_kernel.TILED_ROUNDS (where the
plan switches) can be checked on a GPU.

    python -m benchmarks.tabulated_launch --device cuda [--designs 512] [--worlds 4096 4608 8192 16384]

The designs are repeated to fill each batch (their tables and layouts are made once); each kernel
runs 20 warm-up steps, then 200 timed steps at dt 5 ms. Prints one JSON line a batch and kernel and
writes tabulated_launch_<device>.json, .csv and .png (ms per step against worlds).
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

from benchmarks.run import RESULTS, device_tag


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--designs", type=int, default=512)
    parser.add_argument("--worlds", nargs="+", type=int, default=[4096, 4608, 8192, 16384])
    parser.add_argument("--steps", type=int, default=200)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    import engine
    from engine.reduced.tabulated_kernel import tiled_max_worlds
    from morphopt.build import build_specs
    from morphopt.families import load_family

    family = load_family("walker")
    params = family.space.sample(np.random.default_rng(3), 3 * args.designs)
    specs = [s for s in build_specs(family, params) if not isinstance(s, str)][:args.designs]
    rows = []
    for worlds in args.worlds:
        batch = (specs * (worlds // len(specs) + 1))[:worlds]
        for tiled in (True, False):
            config = engine.SolverConfig(tuning=engine.Tuning(tabulated_tiled=tiled))
            model = engine.pack(batch, device=args.device, dt=0.005, config=config)
            _, state = engine.rollout(model, model.state(), None, 20, record_every=10)
            wp.synchronize()
            t = time.perf_counter()
            engine.rollout(model, state, None, args.steps, record_every=10)
            wp.synchronize()
            rows.append({"worlds": worlds, "tiled": tiled, "ms_per_step": 1e3 * (time.perf_counter() - t) / args.steps})
            print(json.dumps(rows[-1]), flush=True)
    out = {"device": device_tag(args.device), "designs": len(specs), "tiled_max_worlds": tiled_max_worlds(args.device),
           "command": "python -m benchmarks.tabulated_launch " + " ".join(sys.argv[1:]), "rows": rows}
    folder = pathlib.Path(args.out) if args.out else RESULTS / out["device"]
    folder.mkdir(parents=True, exist_ok=True)
    write(out, folder / f"tabulated_launch_{out['device']}")


def write(out: dict, stem: pathlib.Path) -> None:
    """JSON, CSV and a plot of ms per step against worlds, one line a kernel."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stem.with_suffix(".json").write_text(json.dumps(out, indent=1))
    stem.with_suffix(".csv").write_text("worlds,tiled,ms_per_step\n" + "".join(
        f"{r['worlds']},{int(r['tiled'])},{r['ms_per_step']:.4f}\n" for r in out["rows"]))
    fig, ax = plt.subplots(figsize=(5.5, 3.8))
    for tiled, label in ((True, "a block of lanes per world (tiled)"), (False, "one thread per world")):
        rows = [r for r in out["rows"] if r["tiled"] == tiled]
        ax.plot([r["worlds"] for r in rows], [r["ms_per_step"] for r in rows], "o-", label=label)
    if out.get("tiled_max_worlds"):
        ax.axvline(out["tiled_max_worlds"], color="grey", ls=":", label="the plan's switch")
    ax.set(xlabel="worlds", ylabel="ms per step", title=f"tabulated walkers, {out['designs']} designs ({out['device']})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(stem.with_suffix(".png"), dpi=110)
    plt.close(fig)


if __name__ == "__main__":
    main()
