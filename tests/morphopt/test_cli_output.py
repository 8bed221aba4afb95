"""What the command line says (issue 49, item 3): Warp's chatter off stdout, one JSON document from
`demo --json`, a notice when kernels compile, an ETA without the compile time, progress inside a
dynamic generation, and bad study files refused before Warp or the engine is imported."""

import json
import os
import re
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

import morphopt.warp_setup as warp_setup
from morphopt.study import run_study
from morphopt.study_spec import load_study_spec
from toyfamily import toy_study


def morphopt(*args, cwd, env=None):
    """`morphopt ARGS` as a user runs it: a process of its own; returns (status, stdout, stderr)."""
    done = subprocess.run([sys.executable, "-m", "morphopt.cli", *args], cwd=cwd, capture_output=True, text=True,
                          env={**os.environ, **(env or {})}, timeout=300)
    return done.returncode, done.stdout, done.stderr


def test_demo_json_prints_one_json_document_and_verbose_brings_warp_back(tmp_path):
    """stdout of `morphopt demo fourbar --json` parses as one JSON document; Warp's banner and
    module lines appear (on stderr) only with --verbose."""
    status, out, err = morphopt("demo", "fourbar", "--json", "--worlds", "2", "--seconds", "0.05", cwd=tmp_path)
    assert status == 0, err
    assert json.loads(out)["scene"] == "fourbar"
    assert "Warp" not in out + err and "Module" not in out + err
    status, out, err = morphopt("demo", "fourbar", "--json", "--worlds", "2", "--seconds", "0.05", "--verbose",
                                cwd=tmp_path)
    assert status == 0 and json.loads(out)["scene"] == "fourbar"
    assert "Warp 1." in err and "initialized" in err and "Module engine." in err


def test_typo_in_a_study_file_is_reported_before_warp_is_imported(tmp_path):
    """A misspelt key stops `study run` with one line, before Warp or the engine is imported."""
    bad = tmp_path / "bad.toml"
    bad.write_text('[study]\nname = "bad"\nfamily = "four_bar"\ngeneratons = 3\n')
    probe = ("import json, sys\nfrom morphopt.cli import main\nstatus = main(['study', 'run', sys.argv[1]])\n"
             "print(json.dumps({'status': status, 'imported': sorted(m for m in ('warp', 'engine', 'optuna', 'cma') "
             "if m in sys.modules)}))")
    done = subprocess.run([sys.executable, "-c", probe, str(bad)], capture_output=True, text=True, timeout=120)
    assert json.loads(done.stdout) == {"status": 2, "imported": []}
    assert "unknown key 'study.generatons'" in done.stderr and len(done.stderr.strip().splitlines()) == 1


def test_compile_notice_when_the_kernel_cache_lacks_a_study_s_module(monkeypatch, tmp_path, capsys):
    """announce_compile says "compiling kernels (first run only, ~N s)" once when Warp's kernel
    cache lacks the study's first module, and nothing when it holds it."""
    from morphopt.evaluate import evaluate_kinematic
    from morphopt.families import load_family

    family = load_family("four_bar")
    evaluate_kinematic(family, [family.space.default()], samples=16)  # its kernels are in the cache now
    wp = warp_setup.quiet_warp()
    monkeypatch.setattr(warp_setup._State, "announced", False)
    warp_setup.announce_compile(warp_setup.Kernels.KINEMATIC, "cpu")
    assert capsys.readouterr().err == ""
    monkeypatch.setattr(wp.config, "kernel_cache_dir", str(tmp_path))  # an empty cache
    warp_setup.announce_compile(warp_setup.Kernels.KINEMATIC, "cpu")
    warp_setup.announce_compile(warp_setup.Kernels.DYNAMIC, "cpu")
    assert capsys.readouterr().err == "compiling kernels (first run only, ~5 s)\n"


def test_module_load_lines_are_dropped_and_counted_as_compile_time(monkeypatch, capsys):
    """Warp's module load lines reach morphopt's logger: dropped (not verbose), a "(compiled)" one
    adds its time to compile_seconds and announces the compile once."""
    monkeypatch.setattr(warp_setup._State, "announced", False)
    monkeypatch.setattr(warp_setup._State, "compile_s", 1.0)
    logger = warp_setup._Logger()
    logger.info("Module engine.joints 88f43cc load on device 'cpu' took 1917.25 ms  (compiled)")
    logger.info("Module engine.rollout de3415c load on device 'cpu' took 2.50 ms  (cached)")
    logger.info("Warp 1.19.0 initialized:")
    assert warp_setup.compile_seconds() == pytest.approx(2.91725)
    expected = warp_setup.Kernels.DYNAMIC.seconds
    assert capsys.readouterr() == ("", f"compiling kernels (first run only, ~{expected} s)\n")


def test_eta_leaves_out_the_compile_time(tmp_path, monkeypatch, capsys):
    """A first generation that spends 2 s compiling kernels does not slow the bar's rate: three
    generations of a toy study show more than 2 generations per second."""
    import morphopt.study as study_module

    real = study_module.evaluate_kinematic
    calls = []

    def compiling_first(*args, **kwargs):
        if not calls:  # as Warp would on a cold cache: 2 s in the first generation, counted by the logger
            time.sleep(2.0)
            warp_setup._State.compile_s += 2.0
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(study_module, "evaluate_kinematic", compiling_first)
    run_study(load_study_spec(toy_study(tmp_path)), progress=True)
    final = capsys.readouterr().err.replace("\r", "\n").strip().splitlines()[-1]
    rate = float(re.search(r"([0-9.]+)gen/s", final).group(1))
    assert "3/3" in final and rate > 2.0, final


def test_dynamic_generation_reports_steps_worlds_and_falls(tmp_path, capsys):
    """A dynamic study shows a second line while it simulates: steps done of the generation's total,
    worlds running and walkers fallen."""
    run_study(load_study_spec(_dynamic_study(tmp_path)), progress=True)
    err = capsys.readouterr().err.replace("\r", "\n")
    assert "simulating" in err and "/1000" in err and "2 worlds running, 0 fell" in err


def _dynamic_study(tmp_path):
    path = tmp_path / "dyn.toml"
    path.write_text(textwrap.dedent("""
        [study]
        name = "dyn"
        family = "four_bar"
        mode = "dynamic"
        generations = 1
        worlds = 2
        [objective]
        metric = "torque_rms"
        direction = "minimize"
        [simulation]
        duration = 1.0
        dt = 0.001
    """))
    return path


def test_progress_counts_steps_running_worlds_and_falls():
    """evaluate_dynamic's progress wrapper: steps by record, fallen worlds counted once."""
    from morphopt.evaluate import _reporting

    seen = []
    halts = iter([np.array([False, True, False]), np.array([False, True, True])])
    halt = _reporting(lambda points, start: next(halts), lambda *a: seen.append(a), steps=20, record_every=10,
                      worlds=3)
    halt(None, None)
    halt(None, None)
    assert seen == [(10, 20, 2, 1), (20, 20, 1, 2)]
    plain = []
    _reporting(None, lambda *a: plain.append(a), steps=10, record_every=10, worlds=2)(None, None)
    assert plain == [(10, 10, 2, 0)]


@pytest.mark.slow
def test_first_run_says_it_compiles_and_a_second_does_not(tmp_path):
    """With an empty Warp kernel cache a study run says "compiling kernels (first run only, ~N s)"
    on stderr and its stdout holds only morphopt's lines; the next run, cached, says nothing of it."""
    spec = toy_study(tmp_path, generations=2)
    env = {"WARP_CACHE_PATH": str(tmp_path / "kernels")}
    status, out, err = morphopt("study", "run", str(spec), cwd=tmp_path, env=env)
    assert status == 0, err
    assert re.search(r"^compiling kernels \(first run only, ~\d+ s\)$", err, re.M), err
    assert out.startswith("study 'toy': 8 designs") and "Warp" not in out + err and "Module" not in out + err
    status, out, err = morphopt("study", "run", str(spec), "--fresh", cwd=tmp_path, env=env)
    assert status == 0 and "compiling" not in err
