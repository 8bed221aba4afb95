"""engine.config: SolverConfig holds what a user sets, Tuning the method's knobs.

The public field lists are what they are (a new field must be documented where users read it),
tuned() changes the knobs only, the knobs SolverConfig once held are refused with a message that
names Tuning, each plan starts its PADMM at its own penalty unless Tuning.rho says otherwise, the
knobs once set on packed models reach them from the Tuning, and a study file's [solver.tuning]
table is read and checked like [solver].
"""

import dataclasses
import re

import pytest

import engine
from engine import SolverConfig, Tuning
from engine.config import MAXIMAL_RHO, TABULATED_RHO
from engine.reduced.chains import CONTACT_RHO
from engine.scenes import fourbar

SETTINGS = ["integrator", "max_iterations", "tolerance", "relative_tolerance", "position_iterations", "baumgarte",
            "limit_margin", "limit_stabilization", "contact_margin", "contact_stabilization", "restitution_threshold",
            "max_speed", "health_joint_tolerance", "health_angular_tolerance", "health_residual", "tuning"]
# today's defaults of the knobs (rho None: each plan's own), so that every plan steps as before
KNOBS = {"eta": 1e-5, "rho": None, "adaptive_rho": True, "rho_update_interval": 4, "acceleration": True,
         "warmstart": True, "warmstart_decay": 0.05, "cap_joint_penalty": True, "free_rho": 2e-4, "stall_ratio": 0.0,
         "projection_velocity_update": True, "projection_velocity_floor": 1e-7, "projection_skip_floor": 1e-7,
         "projection_skip_floor_angular": 1e-6, "linear_solver": "auto", "step_kernel": "auto",
         "sparse_body_nodes": True, "sparse_projection_pattern": "auto", "sparse_ordering": "minimum_degree",
         "compensated_state": True, "fused_block": None, "fused_registers": None, "fused_inverse": None,
         "fused_sharing": None, "tree_registers": None, "tree_contact_working": None, "tabulated_tiled": None,
         "tabulated_registers": None}


def _entries(cls) -> dict:
    """The Attributes section of ``cls``'s docstring: field name -> its text."""
    doc = cls.__doc__.split("Attributes:", 1)[1]
    entries, name = {}, None
    for line in doc.splitlines():
        match = re.match(r"\s{8}(\w+): (.*)", line)
        if match:
            name = match.group(1)
            entries[name] = match.group(2)
        elif name and line.strip():
            entries[name] += " " + line.strip()
    return entries


def test_the_public_fields_are_the_settings_a_user_sets():
    """SolverConfig's fields are the user's settings and ``tuning``; Tuning's are the knobs, with
    today's defaults. A field added to either without its entry in the class docstring fails here
    (SolverConfig: with its unit in brackets or when to change it)."""
    assert [f.name for f in dataclasses.fields(SolverConfig)] == SETTINGS
    assert {f.name: f.default for f in dataclasses.fields(Tuning)} == KNOBS
    settings = _entries(SolverConfig)
    assert sorted(settings) == sorted(SETTINGS)
    for name, text in settings.items():
        assert "[" in text or "when" in text, (name, text)
    knobs = _entries(Tuning)
    assert sorted(knobs) == sorted(KNOBS)
    assert "Solver tuning: what each knob was measured to do" in " ".join(Tuning.__doc__.split())
    assert engine.Tuning is Tuning and "Tuning" in engine.__all__
    from engine.model import Integrator, SolverConfig as FromModel
    assert FromModel is SolverConfig and Integrator is engine.Integrator


def test_tuned_changes_the_knobs_only():
    """tuned(...) is a copy whose tuning has the changes and whose settings are the same; a name
    that is no Tuning field is refused by name (a SolverConfig field with a hint)."""
    config = SolverConfig(max_iterations=30, tolerance=1e-4, tuning=Tuning(rho_update_interval=8))
    tuned = config.tuned(rho=1.0, step_kernel="staged")
    assert tuned.tuning == Tuning(rho=1.0, step_kernel="staged", rho_update_interval=8)
    assert dataclasses.replace(tuned, tuning=config.tuning) == config
    assert config.tuning.rho is None and config.tuning.step_kernel == "auto"  # the original is unchanged
    with pytest.raises(ValueError, match="'rhoo' is not a field of engine.Tuning"):
        config.tuned(rhoo=1.0)
    with pytest.raises(ValueError, match="'max_iterations' is not a field of engine.Tuning.*dataclasses.replace"):
        config.tuned(max_iterations=3)
    with pytest.raises(ValueError, match="Tuning.step_kernel"):
        config.tuned(step_kernel="megakernel")
    assert SolverConfig(tuning={"rho": 0.5}) == SolverConfig(tuning=Tuning(rho=0.5))  # a mapping reads as Tuning
    with pytest.raises(ValueError, match="unknown Tuning field 'bogus'"):
        SolverConfig(tuning={"bogus": 1})


@pytest.mark.parametrize("name, value", [("rho", 1.0), ("linear_solver", "sparse"), ("step_kernel", "staged"),
                                         ("eta", 1e-4), ("free_rho", 1e-3)])
def test_the_knobs_solver_config_held_are_refused_naming_tuning(name, value):
    """SolverConfig(rho=...), dataclasses.replace(config, rho=...) and config.rho fail, saying that
    the knob is Tuning's now."""
    with pytest.raises(TypeError, match=f"{name} is a field of engine.Tuning.*Tuning\\({name}=.*tuned\\({name}="):
        SolverConfig(**{name: value})
    with pytest.raises(TypeError, match="engine.Tuning"):
        dataclasses.replace(SolverConfig(), **{name: value})
    with pytest.raises(AttributeError, match=f"config.tuning.{name}"):
        getattr(SolverConfig(), name)
    assert getattr(SolverConfig().tuned(**{name: value}).tuning, name) == value


def test_values_are_checked_in_both_classes():
    for bad in (dict(max_iterations=0), dict(tolerance=0.0), dict(baumgarte=2.0), dict(max_speed=float("nan")),
                dict(integrator="rk4"), dict(tuning=5)):
        with pytest.raises(ValueError, match="SolverConfig"):
            SolverConfig(**bad)
    for bad in (dict(rho=0.0), dict(rho=-1.0), dict(rho=float("inf")), dict(eta=0.0), dict(stall_ratio=1.0),
                dict(free_rho=0.0), dict(fused_registers=-1), dict(fused_block=0), dict(tree_contact_working=0),
                dict(tabulated_tiled="yes"), dict(sparse_ordering="nested_dissection"), dict(linear_solver="lu")):
        with pytest.raises(ValueError, match="Tuning"):
            Tuning(**bad)
    assert Tuning(sparse_projection_pattern=True).sparse_projection_pattern == "always"


def test_the_closed_choices_are_enums_given_by_value():
    """Tuning's closed choices become their enum members whether given by value or as members, and
    still compare, print and hash as their strings (code and study files give them as strings);
    anything else is refused with the choices named."""
    from engine.config import LinearSolver, ProjectionPattern, SparseOrdering, StepKernel

    tuning = Tuning(linear_solver="sparse", step_kernel=StepKernel.STAGED, sparse_ordering="shallow")
    assert tuning.linear_solver is LinearSolver.SPARSE and tuning.step_kernel is StepKernel.STAGED
    assert tuning.sparse_ordering is SparseOrdering.SHALLOW
    assert Tuning().sparse_projection_pattern is ProjectionPattern.AUTO
    assert tuning.linear_solver == "sparse" and f"{tuning.step_kernel}" == "staged"
    assert {"sparse": 1}[tuning.linear_solver] == 1
    assert Tuning(linear_solver="sparse") == Tuning(linear_solver=LinearSolver.SPARSE)
    for bad in (1, None, "SPARSE", LinearSolver.SPARSE.name):
        with pytest.raises(ValueError, match="Tuning.linear_solver: expected 'auto', 'dense' or 'sparse'"):
            Tuning(linear_solver=bad)


def _walker():
    from morphopt.families import load_family

    family = load_family("walker")
    return family.build_spec(family.space.validate({**family.space.default(), "legs_per_side": 3}))


def test_each_plan_starts_at_its_own_penalty_unless_tuning_sets_one():
    """Tuning.rho None: the maximal plan's kernels read 1e-3 (padmm_rho_init), the tree plan's
    CONTACT_RHO = 1 (today it ignored the setting; now tuning.rho is its start), the tabulated
    plan's 1 (its step kernel's third input); a set rho reaches every plan."""
    spec = fourbar().spec
    maximal = engine.pack([spec], device="cpu", coordinates="maximal")
    tree = engine.pack([spec], device="cpu", coordinates="tree")
    assert (maximal.plan.coordinates.value, tree.plan.coordinates.value) == ("maximal", "tree")
    assert maximal.padmm_rho_init.numpy()[0] == pytest.approx(MAXIMAL_RHO) and MAXIMAL_RHO == 1e-3
    assert tree.inner.rho_init == CONTACT_RHO == 1.0
    walker = _walker()
    tabulated = engine.pack([walker], device="cpu", coordinates="tabulated")
    assert tabulated.plan.coordinates.value == "tabulated"
    assert tabulated.inner._step_inputs()[2] == TABULATED_RHO == 1.0
    config = SolverConfig().tuned(rho=0.25)
    assert engine.pack([spec], device="cpu", config=config, coordinates="maximal").padmm_rho_init.numpy()[0] == 0.25
    assert engine.pack([spec], device="cpu", config=config, coordinates="tree").inner.rho_init == 0.25
    assert engine.pack([walker], device="cpu", config=config, coordinates="tabulated").inner._step_inputs()[2] == 0.25


def test_the_knobs_set_on_packed_models_come_from_the_tuning():
    """The fused step's lanes, register cap, inverse and sharing, the tree kernel's register cap and
    the tabulated step's form and register cap: None keeps each plan's choice, a value reaches the
    model's attribute (0 registers: the compiler's choice)."""
    from engine.fused import FUSED_REGISTERS
    from engine.reduced.chain_kernel import MAX_REGISTERS
    from engine.reduced.tabulated_kernel import TILED_REGISTERS

    spec = fourbar().spec
    plain = engine.pack([spec], device="cpu", coordinates="maximal")
    assert (plain.fused_block, plain.fused_registers, plain.fused_inverse, plain.fused_sharing) == (
        None, FUSED_REGISTERS, None, None)
    knobs = SolverConfig().tuned(fused_block=1, fused_registers=64, fused_inverse=True, fused_sharing=0)
    model = engine.pack([spec], device="cpu", config=knobs, coordinates="maximal")
    assert (model.fused_block, model.fused_registers, model.fused_inverse, model.fused_sharing) == (1, 64, True, 0)
    config = SolverConfig().tuned(fused_registers=0)
    assert engine.pack([spec], device="cpu", config=config, coordinates="maximal").fused_registers is None
    tree = engine.pack([spec], device="cpu", coordinates="tree")
    assert tree.inner.max_registers == MAX_REGISTERS
    tree = engine.pack([spec], device="cpu", config=SolverConfig().tuned(tree_registers=0), coordinates="tree")
    assert tree.inner.max_registers is None
    walker = _walker()
    tabulated = engine.pack([walker], device="cpu", coordinates="tabulated").inner
    assert not tabulated.tiled and tabulated.max_registers == TILED_REGISTERS  # the CPU: a thread per world
    knobs = SolverConfig().tuned(tabulated_tiled=True, tabulated_registers=0)
    tabulated = engine.pack([walker], device="cpu", config=knobs, coordinates="tabulated").inner
    assert tabulated.tiled and tabulated.max_registers is None


STUDY = """
[study]
name = "tuned"
family = "four_bar"
mode = "dynamic"
[objective]
metric = "torque_rms"
direction = "minimize"
[simulation]
duration = 1.0
dt = 0.002
[solver]
max_iterations = 30
{solver}
"""


def test_a_study_files_solver_tuning_table_is_read_and_checked(tmp_path):
    """[solver.tuning] holds Tuning's fields (studies/walker.toml's rho_update_interval, its rho
    left to the plan); an unknown key there, or a knob in [solver], is refused naming the file and
    the key."""
    from morphopt.study_spec import load_study_spec

    path = tmp_path / "tuned.toml"
    path.write_text(STUDY.format(solver="[solver.tuning]\nrho_update_interval = 8\nlinear_solver = 'dense'"))
    spec = load_study_spec(path)
    assert spec.solver_config() == SolverConfig(max_iterations=30,
                                                tuning=Tuning(rho_update_interval=8, linear_solver="dense"))
    for solver, key in (("[solver.tuning]\nrho_updates = 8", "'solver.tuning.rho_updates'"),
                        ("rho_update_interval = 8", "'solver.rho_update_interval' ('rho_update_interval' is a "
                                                    "field of engine.Tuning: put it under [solver.tuning])")):
        path.write_text(STUDY.format(solver=solver))
        with pytest.raises(ValueError) as refused:
            load_study_spec(path)
        assert str(path) in str(refused.value) and f"unknown key {key}" in str(refused.value)
        assert "\n" not in str(refused.value)
    walker = load_study_spec(engine.__path__[0] + "/../studies/walker.toml").solver_config()
    assert walker.tuning.rho is None and walker.tuning.rho_update_interval == 8 and walker.max_iterations == 30
