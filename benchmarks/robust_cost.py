"""What robustness costs: a generation of D designs x K scenarios against one of D x (K + 1) plain
designs, the same number of worlds (walkers, slopes and payloads; with --tolerance also a 1 %
scale tolerance, which gives every scenario its own geometry). --plain N sets the plain batch's
size instead (e.g. 512 designs x 8 scenarios against 4096 plain designs).

    python -m benchmarks.robust_cost [--device cpu] [--designs 64] [--samples 7] [--plain N] [--out DIR]

Times evaluate_dynamic on the plain batch and morphopt.robust.robust_evaluation on the robust one,
each twice (the first compiles), and writes robust_cost_<device>.json.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

from benchmarks.run import RESULTS, device_tag
from morphopt.evaluate import evaluate_dynamic
from morphopt.families import load_family
from morphopt.robust import Distribution, Robustness, robust_evaluation, scenario_hooks


class _Spec:  # the fields robust_evaluation reads
    seed, metric, direction = 0, "walking_speed", "maximize"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--designs", type=int, default=64)
    parser.add_argument("--samples", type=int, default=7)
    parser.add_argument("--plain", type=int, default=None, help="plain designs (default: designs x (samples + 1))")
    parser.add_argument("--tolerance", action="store_true")
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    family = load_family("walker")
    rng = np.random.default_rng(0)
    worlds = args.plain or args.designs * (args.samples + 1)
    params = []
    while len(params) < max(worlds, args.designs):
        for p in family.space.sample(rng, worlds):
            try:
                params.append(family.space.validate({**p, "legs_per_side": 3}))
            except ValueError:
                continue
    params = params[:max(worlds, args.designs)]
    robust = Robustness(samples=args.samples, slope=Distribution("uniform", low=-5.0, high=5.0),
                        payload=Distribution("uniform", low=0.0, high=0.3),
                        parameters={"scale": Distribution("normal", 0.0, 0.01)} if args.tolerance else {})
    kwargs = dict(duration=2.0, dt=0.005, device=args.device)

    def plain():
        return evaluate_dynamic(family, params[:worlds], **kwargs)

    def robustly():
        return robust_evaluation(_Spec, robust, family.space, params[:args.designs], 0,
                                 lambda batch, scenarios: evaluate_dynamic(family, batch,
                                                                           spec_hook=scenario_hooks(batch, scenarios),
                                                                           **kwargs),
                                 lambda ev: np.array([-m.get("walking_speed", np.nan) if not f else np.inf
                                                      for m, f in zip(ev.metrics, ev.failures)]))[0]

    out = {"device": device_tag(args.device), "plain_worlds": worlds,
           "robust_worlds": args.designs * (args.samples + 1), "designs": args.designs, "samples": args.samples,
           "tolerance": args.tolerance, "command": "python -m benchmarks.robust_cost " + " ".join(sys.argv[1:])}
    for name, run in (("plain", plain), ("robust", robustly)):
        seconds = []
        for _ in range(2):
            t = time.perf_counter()
            evaluation = run()
            seconds.append(time.perf_counter() - t)
        out[name] = {"seconds": seconds[-1], "timings": {k: round(v, 3) for k, v in evaluation.timings.items()}}
    out["robust_over_plain"] = out["robust"]["seconds"] / out["plain"]["seconds"]
    print(json.dumps(out), flush=True)
    folder = pathlib.Path(args.out) if args.out else RESULTS / out["device"]
    folder.mkdir(parents=True, exist_ok=True)
    suffix = ("_tolerance" if args.tolerance else "") + (f"_plain{args.plain}" if args.plain else "")
    (folder / f"robust_cost_{out['device']}{suffix}.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
