"""engine.reduced.model.pack_facts over a batch equals the facts of each spec alone, to the last bit."""

import numpy as np

from engine.reduced.model import pack_facts
from morphopt.families import load_family
from morphopt.linkage.to_spec import to_spec


def _alone(spec) -> tuple:
    """The facts of one spec, world by world as the reduced models first computed them."""
    extent = max(float(np.abs(b.position).max()) for b in spec.bodies)
    mass, ratio = {b.name: b.mass for b in spec.bodies}, 1.0
    for j in spec.joints:
        if j.parent is not None:
            ratio = max(ratio, mass[j.parent] / mass[j.child], mass[j.child] / mass[j.parent])
    return extent, ratio


def test_pack_facts_of_a_batch_equal_each_spec_alone():
    """Walkers of both leg families and one to four legs per side, and a four-bar on the world
    (world joints only count against no mass), in one call and one by one."""
    walker, four_bar = load_family("walker"), load_family("four_bar")
    designs = [walker.space.default(), {**walker.space.default(), "leg_family": "klann_leg", "legs_per_side": 1}]
    designs += walker.space.sample(np.random.default_rng(3), 12)
    specs = [s for s in walker.build_specs([walker.space.validate(p) for p in designs]) if not isinstance(s, Exception)]
    specs.insert(2, to_spec(four_bar.generate(four_bar.space.default())))
    assert len(specs) > 8
    extent, ratio = pack_facts(specs)
    for w, spec in enumerate(specs):
        alone = _alone(spec)
        assert extent[w] == alone[0] and ratio[w] == alone[1]
    assert pack_facts(specs[:1])[0][0] == _alone(specs[0])[0]
