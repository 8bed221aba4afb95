"""tabulated_layout's array path gives the item-by-item analysis's layout to the last bit.

engine.reduced.tabulated_layout reads a spec with arrays (every body and joint at once, sub-chains
of one structure together, structure facts cached); _plain_layout is the analysis one item at a
time, every check in order. For walkers of every topology, a base frame turned off the plane
normal and a lone four-bar, both must give equal layouts (every number bit for bit, the same table
objects); a spec the array path does not take as it is (a strided array) or refuses (a joint limit)
goes through _plain_layout, with its result or its error. Specs analysed together (tabulated_layouts,
as engine.pack plans a study's generation) get the layouts each gets alone.
"""

import dataclasses
import math

import numpy as np
import pytest

from engine import Body, MechanismSpec
from engine.reduced import tabulated_layout as layout_module
from engine.reduced import tabulated_tables as tables_module
from engine.reduced.tabulated_layout import tabulated_layout
from engine.reduced.tabulated_plain import _plain_layout
from engine.reduced.tabulated_tables import TABLE_SAMPLES, SubChainTable
from morphopt.families import load_family
from morphopt.linkage import Crank, Dyad, Link, Linkage
from morphopt.linkage.to_spec import BarStyle, linkage_parts

WALKER = load_family("walker")


def _leaves(obj, path="layout"):
    """Every number of a layout as (path, kind, exact value); tables by identity; the spec left out."""
    if isinstance(obj, SubChainTable):
        return [(path, "table", id(obj))]
    if isinstance(obj, np.ndarray):
        return [(path, "array", obj.dtype.str, obj.shape, np.ascontiguousarray(obj).tobytes())]
    if isinstance(obj, (float, np.floating)):
        return [(path, type(obj).__name__, np.float64(obj).tobytes())]
    if obj is None or isinstance(obj, (bool, int, str, np.integer)):
        return [(path, type(obj).__name__, obj)]
    if dataclasses.is_dataclass(obj):
        return [leaf for f in dataclasses.fields(obj) if f.name != "spec"
                for leaf in _leaves(getattr(obj, f.name), f"{path}.{f.name}")]
    if isinstance(obj, (list, tuple)):
        return [(path, type(obj).__name__, len(obj))] + [leaf for i, item in enumerate(obj)
                                                         for leaf in _leaves(item, f"{path}[{i}]")]
    raise AssertionError(f"{path}: unexpected {type(obj).__name__}")


def _assert_same_layout(spec):
    structure = layout_module._analyse(spec)
    assert structure is not None
    fast = layout_module._array_layout(spec, structure, TABLE_SAMPLES)
    assert fast is not None, "the array path should take this spec"
    plain = _plain_layout(spec)
    a, b = _leaves(fast), _leaves(plain)
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert x == y, f"{x[0]} differs"
    assert _leaves(tabulated_layout(spec)) == b


def _walkers():
    rng = np.random.default_rng(21)
    designs = [{**WALKER.space.default(), "leg_family": family, "legs_per_side": count}
               for family in ("jansen_leg", "klann_leg") for count in (1, 2, 3, 4)]
    return designs + WALKER.space.sample(rng, 6)


@pytest.mark.parametrize("index", range(14))
def test_walker_layouts_equal_the_item_by_item_analysis(index):
    """Both leg families, one to four legs per side, random walkers."""
    _assert_same_layout(WALKER.build_spec(_walkers()[index]))


def _turned(spec, angle=0.5 * math.pi):
    """``spec`` with its base (body 0) frame turned by ``angle`` about z: joints now turn about the
    base frame's x axis (the state frame is no longer the base frame)."""
    c, s = math.cos(angle), math.sin(angle)
    G = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    g = np.array([0.0, 0.0, math.sin(0.5 * angle), math.cos(0.5 * angle)])

    def mul(a, b):
        av, aw, bv, bw = a[:3], a[3], b[:3], b[3]
        return np.concatenate([aw * bv + bw * av + np.cross(av, bv), [aw * bw - av @ bv]])

    g_inv = g * np.array([-1.0, -1.0, -1.0, 1.0])
    base = spec.bodies[0]
    bodies = [dataclasses.replace(base, orientation=mul(base.orientation, g), com=G.T @ base.com,
                                  inertia=G.T @ base.inertia @ G), *spec.bodies[1:]]
    joints = [dataclasses.replace(j, parent_position=G.T @ j.parent_position,
                                  parent_orientation=mul(g_inv, j.parent_orientation)) if j.parent == base.name else j
              for j in spec.joints]
    shapes = [dataclasses.replace(sh, position=G.T @ sh.position, orientation=mul(g_inv, sh.orientation))
              if sh.body == base.name else sh for sh in spec.shapes]
    points = [dataclasses.replace(p, position=G.T @ p.position) if p.body == base.name else p for p in spec.points]
    return dataclasses.replace(spec, bodies=bodies, joints=joints, shapes=shapes, points=points)


def _four_bar():
    base = Body("base", 1.0, np.diag([0.01, 0.02, 0.02]), position=(0.0, 0.0, 1.0))
    linkage = Linkage("four_bar", ground={"O": (0.0, 0.0), "A": (0.2, 0.0)}, crank=Crank("O", "M", 0.05, speed=3.0),
                      dyads=[Dyad("B", "M", 0.2, "A", 0.1)],
                      links=[Link("crank", ("O", "M")), Link("coupler", ("M", "B")), Link("rocker", ("A", "B"))],
                      points={"tip": "B"})
    bodies, joints, points = linkage_parts(linkage, base=base, origin=(0.0, 0.0, 1.0), style=BarStyle(),
                                           crank_damping=5.0, effort_limit=10.0)
    return MechanismSpec([base, *bodies], joints, points, name="four_bar")


def test_turned_base_and_a_lone_four_bar_equal_the_item_by_item_analysis():
    walker = WALKER.build_spec({**WALKER.space.default(), "legs_per_side": 2})
    _assert_same_layout(_turned(walker))
    _assert_same_layout(_turned(walker, 0.3))
    _assert_same_layout(_four_bar())


def test_specs_from_another_process_take_the_array_path(monkeypatch):
    """A spec unpickled (built in a worker process: morphopt.build's pool) holds float64 arrays whose
    dtype is an equal but other object: the array path takes it all the same (before, every such
    spec went item by item, 6 ms each: 4 s for 1,024 walkers built by a pool of 8), and its layout
    equals the original's."""
    import pickle

    specs = [WALKER.build_spec({**WALKER.space.default(), "legs_per_side": 3, "scale": sc}) for sc in (2.5, 3.5)]
    copies = [pickle.loads(pickle.dumps(spec)) for spec in specs]
    assert copies[0].bodies[1].com.dtype is not np.dtype(np.float64)  # the condition this guards
    plain = []
    original = layout_module._plain
    monkeypatch.setattr(layout_module, "_plain", lambda spec, samples: plain.append(1) or original(spec, samples))
    made = layout_module.tabulated_layouts(copies)
    assert plain == []
    for spec, layout in zip(specs, made):
        assert _leaves(layout) == _leaves(tabulated_layout(spec))


def test_what_the_array_path_does_not_take_goes_item_by_item():
    """A strided array in the spec: the array path steps aside, the layout is _plain_layout's. A
    refused spec: the same error as _plain_layout's."""
    spec = WALKER.build_spec(WALKER.space.default())
    strided = np.empty(6)
    strided[::2] = spec.bodies[3].com
    spec.bodies[3].com = strided[::2]
    structure = layout_module._analyse(spec)
    assert layout_module._array_layout(spec, structure, TABLE_SAMPLES) is None
    assert _leaves(tabulated_layout(spec)) == _leaves(_plain_layout(spec))
    limited = WALKER.build_spec(WALKER.space.default())
    limited.joints[5].limit_upper = 1.0
    with pytest.raises(ValueError) as plain:
        _plain_layout(limited)
    with pytest.raises(ValueError, match="has limits") as fast:
        tabulated_layout(limited)
    assert str(fast.value) == str(plain.value)


def _with_tables(leaves, layouts):
    """``leaves`` with every table identity replaced by the table's numbers (bytes)."""
    tables = {id(chain.table): chain.table for lay in layouts if not isinstance(lay, Exception) for chain in lay.groups}
    out = []
    for leaf in leaves:
        if leaf[1] == "table":
            table = tables[leaf[2]]
            leaf = (leaf[0], "table", tuple(np.asarray(getattr(table, f)).tobytes() for f in
                                            ("links", "links_d1", "links_d2", "contact", "contact_d1", "contact_d2",
                                             "contact_link", "closure_error")), table.key)
        out.append(leaf)
    return out


def _outcomes(specs, together: bool) -> list:
    """Per spec the leaves of its layout (tables by their numbers) or its error, from an empty table
    cache: analysed together (tabulated_layouts) or one tabulated_layout call per spec."""
    tables_module._TABLES.clear()
    if together:
        made = layout_module.tabulated_layouts(specs)
    else:
        made = []
        for spec in specs:
            try:
                made.append(tabulated_layout(spec))
            except ValueError as exc:
                made.append(exc)
    return [f"{type(m).__name__}: {m}" if isinstance(m, Exception) else _with_tables(_leaves(m), made) for m in made]


def test_layouts_analysed_together_equal_each_alone():
    """tabulated_layouts (one array pass per structure, as a study's generation is planned) gives
    every spec the layout tabulated_layout gives it alone, every number and table to the last bit,
    the tables made in the same order: for walkers of one topology in other dimensions, and for a
    mixed batch (both leg families, one to four legs per side, a turned base, a lone four-bar, a
    spec the array path leaves to the item-by-item analysis and one it refuses, repeated specs)."""
    rng = np.random.default_rng(8)
    same = [{**p, "leg_family": "jansen_leg", "legs_per_side": 3} for p in WALKER.space.sample(rng, 12)]
    same_specs = [WALKER.build_spec(p) for p in same]
    assert len({layout_module._structure_key(s) for s in same_specs}) == 1
    assert _outcomes(same_specs, together=True) == _outcomes(same_specs, together=False)

    strided = WALKER.build_spec(same[0])
    column = np.empty(6)
    column[::2] = strided.bodies[3].com
    strided.bodies[3].com = column[::2]
    limited = WALKER.build_spec(same[1])
    limited.joints[5].limit_upper = 1.0
    bent = WALKER.build_spec(same[2])  # taken by the array path's first checks, refused by its plane check
    bent.joints[4].axis = np.array([0.0, -0.8, 0.6])
    ragged = WALKER.build_spec(same[3])  # its arrays do not stack with the batch's
    ragged.bodies[2].orientation = (0.0, 0.0, 1.0)
    mixed = [WALKER.build_spec(p) for p in _walkers()] + [_turned(WALKER.build_spec(
        {**WALKER.space.default(), "legs_per_side": 2})), _four_bar(), strided, limited, bent, ragged] + same_specs[:3]
    mixed.insert(3, mixed[0])  # one spec object twice
    together, alone = _outcomes(mixed, together=True), _outcomes(mixed, together=False)
    assert together == alone
    errors = [o for o in together if isinstance(o, str)]
    assert len(errors) == 3 and "has limits" in errors[0] and "turns about" in errors[1], errors


def test_analyses_made_elsewhere_give_the_same_layouts():
    """tabulated_analyses made in another process (here: a pickle round trip, as morphopt.build's
    workers send them) and handed to tabulated_layouts give every spec the layout it gets without
    them, to the last bit, for the mixed batch's specs too (the item-by-item ones and the refused
    ones); entries that belong to another spec of the same structure (the batch's order slipped),
    another sample count, or another structure are not used, and the result is still the same."""
    import pickle

    rng = np.random.default_rng(9)
    same = [WALKER.build_spec({**p, "leg_family": "jansen_leg", "legs_per_side": 2})
            for p in WALKER.space.sample(rng, 6)]
    limited = WALKER.build_spec(WALKER.space.default())
    limited.joints[5].limit_upper = 1.0
    specs = same + [WALKER.build_spec(p) for p in _walkers()[:4]] + [_four_bar(), limited]
    analyses = pickle.loads(pickle.dumps(layout_module.tabulated_analyses(specs)))
    assert len(analyses) == len(specs) and analyses[-1][2] is None  # limited: left to the item-by-item path
    baseline = _outcomes(specs, together=True)
    tables_module._TABLES.clear()
    given = layout_module.tabulated_layouts(specs, analyses=analyses)
    assert [f"{type(m).__name__}: {m}" if isinstance(m, Exception) else _with_tables(_leaves(m), given)
            for m in given] == baseline

    calls = []
    original = layout_module._pending_layouts

    def counting(batch, st, samples):
        calls.append(len(batch))
        return original(batch, st, samples)

    layout_module._pending_layouts = counting
    try:
        layout_module.tabulated_layouts(same, analyses=analyses[:len(same)])
        assert calls == []  # every entry used
        slipped = analyses[1:len(same)] + analyses[:1]
        assert _leaves_of(layout_module.tabulated_layouts(same, analyses=slipped)) == _leaves_of(
            layout_module.tabulated_layouts(same))
        assert calls[0] == len(same)  # no entry matched its spec's masses: all analysed here
        calls.clear()
        import copy
        moved = copy.deepcopy(same[0])  # the same masses, one body elsewhere
        moved.bodies[0].position = moved.bodies[0].position + np.array([1e-3, 0.0, 0.0])
        layout_module.tabulated_layouts([moved], analyses=analyses[:1])
        assert calls == [1]
        calls.clear()
        other = [(tie, s + 1, n) for tie, s, n in analyses[:len(same)]]
        layout_module.tabulated_layouts(same, analyses=other)
        assert calls == [len(same)]
        calls.clear()
        layout_module.tabulated_layouts(same[:2], analyses=[analyses[len(same)], None])  # another structure, none
        assert calls == [2]
    finally:
        layout_module._pending_layouts = original


def _leaves_of(layouts):
    return [_leaves(m) for m in layouts]
