"""Specs built by worker processes are the specs built here, to the last bit; failures keep their reasons."""

import types

import numpy as np
import pytest
import warp as wp

from engine import pack_worlds
from morphopt.build import build_specs
from morphopt.families import load_family


def _packed(specs):
    model = pack_worlds(specs, device="cpu")
    return {name: value.numpy() for name, value in vars(model).items() if isinstance(value, wp.array)}


def test_worker_processes_build_the_same_specs_and_failures():
    family = load_family("walker")
    params = family.space.sample(np.random.default_rng(5), 5)
    params.insert(2, {**params[0], "scale": 1.0e9})  # outside the design space: a reason, not a crash
    here = build_specs(family, params, workers=1)
    pooled = build_specs(family, params, workers=2)
    assert len(pooled) == len(params)
    assert isinstance(here[2], str) and here[2] == pooled[2] and "'scale'" in here[2]
    built_here = [s for s in here if not isinstance(s, str)]
    built_pooled = [s for s in pooled if not isinstance(s, str)]
    assert [s.name for s in built_here] == [s.name for s in built_pooled] and len(built_here) >= 4
    a, b = _packed(built_here), _packed(built_pooled)
    assert a.keys() == b.keys() and len(a) > 40
    for name in a:
        assert a[name].dtype == b[name].dtype and np.array_equal(a[name], b[name]), name


def test_a_family_without_a_file_is_built_here_and_bad_worker_counts_are_refused():
    four_bar = load_family("four_bar")
    calls = []

    def build_spec(params, crank_speed=None):
        calls.append(params)
        return four_bar_spec

    four_bar_spec = build_specs(four_bar, [four_bar.space.default()], workers=1)[0]
    family = types.SimpleNamespace(space=four_bar.space, build_spec=build_spec)  # no module file
    out = build_specs(family, [four_bar.space.default()] * 3, workers=2)
    assert out == [four_bar_spec] * 3 and len(calls) == 3  # built in this process
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="workers must be a positive integer"):
            build_specs(four_bar, [four_bar.space.default()], workers=bad)


def test_equal_designs_share_one_built_spec_only_when_asked():
    """share=True builds each distinct design once (the same values in any key order are one
    design) and hands its one spec, or its one failure reason, to every equal design; the specs
    pack to what building each design alone gives."""
    family = load_family("walker")
    a, b = family.space.sample(np.random.default_rng(7), 2)
    bad = {**a, "scale": 1.0e9}
    params = [a, b, dict(reversed(list(a.items()))), bad, {**a}, dict(bad)]
    calls = []
    original = family.build_specs

    def counting(designs, crank_speed=None):
        calls.append(len(designs))
        return original(designs, crank_speed=crank_speed)

    family.build_specs = counting
    try:
        shared = build_specs(family, params, workers=1, share=True)
        assert calls == [2]  # a and b; bad fails its check before any build
        alone = build_specs(family, params, workers=1)
    finally:
        family.build_specs = original
    assert shared[0] is shared[2] is shared[4] and shared[1] is not shared[0]
    assert isinstance(shared[3], str) and shared[3] == shared[5] == alone[3]
    assert len({id(s) for s in alone}) == len(alone)  # not asked: one object a design
    x, y = _packed([s for s in shared if not isinstance(s, str)]), _packed([s for s in alone if not isinstance(s, str)])
    for name in x:
        assert np.array_equal(x[name], y[name]), name


def test_design_keys_tell_arrays_apart_by_every_bit():
    from morphopt.build import _design_key

    a = {"x": np.array([1.0, 2.0]), "n": 3}
    assert _design_key(a) == _design_key({"n": 3, "x": np.array([1.0, 2.0])})
    assert _design_key(a) != _design_key({"x": np.array([1.0, 2.0 + 1e-12]), "n": 3})  # repr would round these
    assert _design_key({"b": True}) != _design_key({"b": 1}) and _design_key({"v": 0.0}) != _design_key({"v": -0.0})


def test_worker_processes_prepare_the_pack_and_the_evaluation_is_the_same(monkeypatch):
    """build_prepared's workers (three or more) also make engine.prepare of their specs (None for a
    design that failed; no list at all where the batch was built here or by two); packing with it gives the worlds the
    same motion to the last bit, and evaluate_dynamic, which passes it on, the same metrics."""
    import pickle

    import engine
    from morphopt.build import build_prepared
    from morphopt.evaluate import evaluate_dynamic

    family = load_family("walker")
    params = family.space.sample(np.random.default_rng(11), 4)
    params.insert(1, {**params[0], "scale": 1.0e9})
    built, prepared = build_prepared(family, params, workers=3)
    assert len(prepared) == len(params) and prepared[1] is None and isinstance(built[1], str)
    assert build_prepared(family, params, workers=1)[1] is None and build_prepared(family, params, workers=2)[1] is None
    specs = [s for s in built if not isinstance(s, str)]
    entries = [p for p, spec in zip(prepared, built) if not isinstance(spec, str)]
    assert len(entries) == len(specs) and all(p is not None for p in entries)
    with pytest.raises(ValueError, match="prepared has 3 entries for 4 specs"):
        engine.pack(specs, device="cpu", dt=5e-3, prepared=entries[:3])
    from engine.reduced import tabulated_layout

    analyse = tabulated_layout._pending_layouts
    runs = []
    for given in (None, entries, pickle.loads(pickle.dumps(entries))):
        if given is not None:  # every entry is used: nothing is analysed again here
            monkeypatch.setattr(tabulated_layout, "_pending_layouts", None)
        model = engine.pack(specs, device="cpu", dt=5e-3, prepared=given)
        monkeypatch.setattr(tabulated_layout, "_pending_layouts", analyse)
        assert model.plan.coordinates is engine.Coordinates.TABULATED
        trace, final = engine.rollout(model, model.state(), None, 20, record_every=10)
        runs.append((trace.points, final.body_q.numpy()))
    for points, body_q in runs[1:]:
        assert np.array_equal(points, runs[0][0]) and np.array_equal(body_q, runs[0][1])

    kwargs = dict(duration=0.1, dt=5e-3, device="cpu")
    params.append(dict(params[2]))  # a design twice: built once, its one entry handed to both worlds
    here = evaluate_dynamic(family, params, workers=1, **kwargs)
    monkeypatch.setattr(tabulated_layout, "_pending_layouts", None)  # here; the workers keep theirs
    pooled = evaluate_dynamic(family, params, workers=3, **kwargs)
    monkeypatch.setattr(tabulated_layout, "_pending_layouts", analyse)
    assert here.failures == pooled.failures and here.failures[1] and pooled.plan.coordinates.value == "tabulated"
    for a, b in zip(here.metrics, pooled.metrics):
        assert a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a if k != "paths")
        assert a.get("paths", {}).keys() == b.get("paths", {}).keys()
        assert all(np.array_equal(a["paths"][n], b["paths"][n]) for n in a.get("paths", {}))


def test_the_evaluation_runs_without_the_collector_and_restores_it():
    """evaluate_dynamic pauses the cyclic garbage collector while it runs (its progress callback
    sees it off) and leaves it as it found it, on or off, also when it raises; evaluate_kinematic
    pauses it too (its family's generate sees it off)."""
    import gc

    from morphopt.evaluate import evaluate_dynamic

    family = load_family("walker")
    seen = []
    progress = lambda *state: seen.append(gc.isenabled())  # noqa: E731
    was = gc.isenabled()
    try:
        gc.enable()
        evaluate_dynamic(family, [family.space.default()], duration=0.05, dt=5e-3, progress=progress)
        assert seen and not any(seen) and gc.isenabled()
        with pytest.raises(ValueError):
            evaluate_dynamic(family, [family.space.default()], duration=0.05, dt=-1.0)
        assert gc.isenabled()
        gc.disable()
        evaluate_dynamic(family, [family.space.default()], duration=0.05, dt=5e-3)
        assert not gc.isenabled()
        gc.enable()
        from morphopt.evaluate import evaluate_kinematic
        legs = load_family("jansen_leg")
        checked = []
        original = legs.generate

        def generate(*args, **kwargs):
            checked.append(gc.isenabled())
            return original(*args, **kwargs)

        legs.generate = generate
        try:
            assert list(evaluate_kinematic(legs, [legs.space.default()] * 2).feasible) == [True, True]
        finally:
            legs.generate = original
        assert checked and not any(checked) and gc.isenabled()
    finally:
        (gc.enable if was else gc.disable)()


def test_worker_processes_prepare_the_tree_plan_of_linkages(monkeypatch):
    """For linkages (the tree plan: a joint to the world, more geometries than the grounded plan
    takes unasked), build_prepared's workers make each spec's chain_layout; packing with them
    makes none here and gives the same motion to the last bit; an entry moved to another spec of
    the same structure is not used."""
    import engine
    from engine.reduced import chain_layout as chain_layout_module
    from morphopt.build import build_prepared

    family = load_family("jansen_leg")
    params = family.space.sample(np.random.default_rng(4), 40)
    built, prepared = build_prepared(family, params, workers=3, crank_speed=3.0)
    index = [i for i, spec in enumerate(built) if not isinstance(spec, str)]
    specs, entries = [built[i] for i in index], [prepared[i] for i in index]
    assert len(specs) >= 17 and all(entry[1] is not None and entry[1][1].spec is None for entry in entries)
    here = engine.pack(specs, device="cpu", dt=1e-3)
    making = chain_layout_module.chain_layout
    monkeypatch.setattr(chain_layout_module, "chain_layout", None)  # nothing made here
    given = engine.pack(specs, device="cpu", dt=1e-3, prepared=entries)
    monkeypatch.setattr(chain_layout_module, "chain_layout", making)
    assert here.plan.coordinates is given.plan.coordinates is engine.Coordinates.TREE
    runs = [engine.rollout(model, model.state(), None, 30, record_every=10)[0].points for model in (here, given)]
    assert np.array_equal(runs[0], runs[1])
    calls = []
    monkeypatch.setattr(chain_layout_module, "chain_layout", lambda spec: calls.append(spec) or making(spec))
    engine.pack(specs[:2], device="cpu", dt=1e-3, prepared=entries[1:3], coordinates="tree")
    assert calls == specs[:2]  # each entry belongs to the next spec: both made here
