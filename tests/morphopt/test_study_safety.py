"""A study is never lost, mixed or hijacked, tried as users and attackers would, through the CLI:
one writer per study (two real processes), no results overwritten without --fresh, a stale
writer's lease taken over, the effective settings kept for resume, storage failures as one line
(exit 2) that leave no partial generation, and pickled checkpoints that are never unpickled."""

import hashlib
import os
import pathlib
import pickle
import signal
import sqlite3
import subprocess
import sys
import textwrap
import time

import pytest

from morphopt.cli import main

SLOW_FAMILY = '''
"""A crank alone whose designs take a while to build; from the fifth design a process builds that
is not the family's default (checks of the family build the default), each waits while the file
HOLD exists: a writer started with HOLD in place stores its first generation and waits inside its
second until the test removes HOLD."""
import os
import time

from morphopt.design_space import DesignSpace, Float
from morphopt.linkage import Crank, Link, Linkage

space = DesignSpace({"r": Float(0.01, 0.05, default=0.02), "x": Float(-1.0, 1.0, default=0.0)})
CALLS = [0]


def generate(params, *, crank_speed=6.283185307179586, phase=0.0):
    if params != space.default():
        time.sleep(DELAY)
        CALLS[0] += 1
    while CALLS[0] > 4 and os.path.exists(HOLD):
        time.sleep(0.02)
    return Linkage(name="toy", ground={"O": (params["x"], 0.0)},
                   crank=Crank("O", "T", params["r"], phase=phase, speed=crank_speed),
                   links=[Link("crank", ("O", "T"))], points={"tip": "T"})
'''


def study(tmp_path, generations=6, delay=0.0, name="toy", storage="", worlds=4) -> str:
    """A kinematic toy study (CMA-ES) whose family sleeps ``delay`` s per design."""
    family = SLOW_FAMILY.replace("DELAY", repr(delay)).replace("HOLD", repr(str(tmp_path / "hold")))
    (tmp_path / f"{name}_family.py").write_text(family)
    path = tmp_path / f"{name}.toml"
    path.write_text(textwrap.dedent(f"""
        [study]
        name = "{name}"
        family = "{name}_family.py"
        generations = {generations}
        worlds = {worlds}
        seed = 5
        {f'storage = "{storage}"' if storage else ""}
        [objective]
        metric = "tip_step_height"
        direction = "maximize"
        [simulation]
        samples = 16
    """))
    return str(path)


def rename(spec, old: str) -> None:
    """Point a study file written as study ``old`` at study 'toy' (another way into its database)."""
    path = pathlib.Path(spec)
    path.write_text(path.read_text().replace(f'name = "{old}"', 'name = "toy"').replace(f"{old}_family", "toy_family"))


def cli(*argv, cwd=None):
    """A real `morphopt` process (not started: Popen)."""
    return subprocess.Popen([sys.executable, "-m", "morphopt.cli", *argv], cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def finish(process, timeout=240) -> tuple[int, str, str]:
    out, err = process.communicate(timeout=timeout)
    return process.returncode, out, err


def error_line(err: str) -> str:
    """The one line of a refused command (progress bars and Warp's lines aside)."""
    lines = [line for line in err.splitlines() if line.startswith("morphopt ")]
    assert "Traceback" not in err and len(lines) == 1, repr(err[-1500:])
    return lines[0]


def rows(database, study="toy") -> list:
    with sqlite3.connect(database) as connection:
        found = connection.execute("SELECT generation, member, value FROM designs WHERE study = ? "
                                   "ORDER BY generation, member", (study,)).fetchall()
    connection.close()
    return found


def studies(database) -> dict:
    with sqlite3.connect(database) as connection:
        found = dict(connection.execute("SELECT study, count(*) FROM designs GROUP BY study").fetchall())
    connection.close()
    return found


def lease_holder(database, study):
    """The pid holding the study's lease, or None."""
    with sqlite3.connect(database) as connection:
        row = connection.execute("SELECT pid, owner FROM studies WHERE name = ?", (study,)).fetchone()
    connection.close()
    return row[0] if row and row[1] else None


def stored_generations(database) -> int:
    """How many generations the database holds (0 while it or its tables do not exist)."""
    try:
        with sqlite3.connect(f"file:{database}?mode=ro", uri=True) as connection:
            done = connection.execute("SELECT max(generation) FROM checkpoints").fetchone()[0]
        connection.close()
    except sqlite3.OperationalError:
        return 0
    return 0 if done is None else done + 1


def wait_for_generation(database, generation, process, timeout=120) -> None:
    """Until the study stored ``generation`` (the process still running)."""
    end = time.time() + timeout
    while time.time() < end:
        if process.poll() is not None:
            raise AssertionError(f"the writer ended early: {process.communicate()}")
        if stored_generations(database) > generation:
            return
        time.sleep(0.1)
    raise AssertionError("no generation was stored in time")


@pytest.mark.slow
def test_two_writers_never_interleave(tmp_path):
    """Two `study run` started together on a new study: one runs (exit 0), the other is refused with
    the writer's pid and host (exit 2); while it runs, a fresh run and a resume are refused too. The
    database then holds one optimizer's designs, each (generation, member) once."""
    spec = study(tmp_path, generations=4, delay=0.1)
    database = tmp_path / "toy.sqlite"
    (tmp_path / "hold").touch()  # the writer stores its first generation and waits inside its second
    first, second = cli("study", "run", spec, cwd=tmp_path), cli("study", "run", spec, cwd=tmp_path)
    while stored_generations(database) < 1 and (first.poll() is None or second.poll() is None):
        time.sleep(0.02)
    late = [cli("study", *argv, cwd=tmp_path) for argv in (("run", spec, "--fresh"), ("resume", spec))]
    for process in late:
        process.wait(timeout=240)
    (tmp_path / "hold").unlink()
    results = {process.pid: finish(process) for process in (first, second, *late)}
    winners = [pid for pid in (first.pid, second.pid) if results[pid][0] == 0]
    assert len(winners) == 1, results
    for pid, (status, _, err) in results.items():
        if pid != winners[0]:
            line = error_line(err)
            busy = f"is being written by pid {winners[0]} on host " in line and "--steal" in line
            # a loser of the two simultaneous starts that comes late (a busy machine) finds results instead
            stored = pid in (first.pid, second.pid) and "already has 4 designs in 1 generations" in line
            assert status == 2 and (busy or stored), line
    stored = rows(database)
    assert [(g, m) for g, m, _ in stored] == [(g, m) for g in range(4) for m in range(4)]
    assert studies(database) == {"toy": 16}


def test_run_never_overwrites_and_fresh_moves_aside(tmp_path):
    """`study run` on a study with results refuses (one line, the database file unchanged, bit for
    bit); `--fresh` runs again and keeps the earlier designs under a new name."""
    spec = study(tmp_path, generations=2)
    assert main(["study", "run", spec]) == 0
    database = tmp_path / "toy.sqlite"
    digest = hashlib.sha256(database.read_bytes()).hexdigest()
    first = rows(database)
    status, _, err = finish(cli("study", "run", spec, "--generations", "3", cwd=tmp_path))
    line = error_line(err)
    assert status == 2 and "already has 8 designs in 2 generations" in line and "--fresh" in line
    assert hashlib.sha256(database.read_bytes()).hexdigest() == digest
    assert main(["study", "run", spec, "--fresh", "--generations", "3"]) == 0
    kept = {name: count for name, count in studies(database).items() if name.startswith("toy.before-")}
    assert list(kept.values()) == [8] and studies(database)["toy"] == 12
    assert rows(database, next(iter(kept))) == first  # moved aside exactly as stored


def test_resume_keeps_the_runs_overrides_and_extends(tmp_path, capsys):
    """A study run with --worlds and --generations on the command line resumes with them; `resume
    --generations` extends it; the result equals an uninterrupted run with the same settings. A
    study file changed since is refused by name."""
    spec = study(tmp_path, generations=3)
    assert main(["study", "run", spec, "--worlds", "6", "--generations", "2"]) == 0
    assert main(["study", "resume", spec]) == 0  # nothing left: the run's own 2 generations are done
    assert "12 designs" in capsys.readouterr().out
    assert main(["study", "resume", spec, "--generations", "5"]) == 0
    resumed = capsys.readouterr().out
    assert "30 designs" in resumed
    assert main(["study", "show", spec]) == 0 and "5/5 generations, 30 designs" in capsys.readouterr().out
    other = tmp_path / "other"
    other.mkdir()
    uninterrupted = study(other, generations=5)
    assert main(["study", "run", uninterrupted, "--worlds", "6"]) == 0
    best = [line for line in capsys.readouterr().out.splitlines() if line.startswith("best") or "=" in line]
    assert best == [line for line in resumed.splitlines() if line.startswith("best") or "=" in line]
    path = pathlib.Path(spec)
    path.write_text(path.read_text().replace("samples = 16", "samples = 24"))
    assert main(["study", "resume", spec, "--generations", "6"]) == 2
    assert "'samples' was 16, is now 24" in capsys.readouterr().err


@pytest.mark.slow
def test_a_killed_writer_is_taken_over_and_a_stolen_lease_stops_its_writer(tmp_path):
    """kill -9 leaves a lease whose process is gone: resume takes it over at once and ends like an
    uninterrupted run. A live writer's lease is taken only with --steal; the writer then stops at its
    next generation without storing it (exit 2), and no generation is stored twice."""
    spec = study(tmp_path, generations=4, delay=0.1)
    database = tmp_path / "toy.sqlite"
    (tmp_path / "hold").touch()  # killed inside its second generation, for certain
    victim = cli("study", "run", spec, cwd=tmp_path)
    wait_for_generation(database, 0, victim)
    time.sleep(0.3)
    victim.send_signal(signal.SIGKILL)
    (tmp_path / "hold").unlink()
    victim.wait()
    status, out, err = finish(cli("study", "resume", spec, cwd=tmp_path))
    assert status == 0, err
    reference = tmp_path / "ref"
    reference.mkdir()
    status, out_ref, err = finish(cli("study", "run", study(reference, generations=4, delay=0.0), cwd=reference))
    assert status == 0 and out.split("best", 1)[1] == out_ref.split("best", 1)[1]

    spec = study(tmp_path, generations=4, delay=0.1, name="steal")
    database = tmp_path / "steal.sqlite"
    (tmp_path / "hold").touch()  # the writer waits inside its second generation, the thief in its third
    writer = cli("study", "run", spec, cwd=tmp_path)
    wait_for_generation(database, 0, writer)
    polite, thief = cli("study", "resume", spec, cwd=tmp_path), cli("study", "resume", spec, "--steal", cwd=tmp_path)
    status, _, err = finish(polite)
    assert status == 2 and "is being written by pid" in error_line(err)
    while lease_holder(database, "steal") != thief.pid:
        assert thief.poll() is None, thief.communicate()
        time.sleep(0.02)
    (tmp_path / "hold").unlink()
    status, out, err = finish(writer)
    assert status == 2, (status, out, err)
    assert "this run lost the study's lease to " in error_line(err), err
    status, _, err = finish(thief)
    assert status == 0, err
    stored = rows(database, "steal")
    assert [(g, m) for g, m, _ in stored] == [(g, m) for g in range(4) for m in range(4)]


def test_storage_failures_are_one_line_before_any_work(tmp_path, capsys):
    """A read-only, locked or damaged database stops the command with one line (exit 2) before
    the first generation is computed; the stored data stays as it was."""
    spec = study(tmp_path, generations=1)
    assert main(["study", "run", spec]) == 0
    database = tmp_path / "toy.sqlite"
    before = rows(database)
    read_only = study(tmp_path, generations=2, name="ro", storage=f"sqlite:///file:{database}?mode=ro&uri=true")
    rename(read_only, "ro")
    assert main(["study", "resume", read_only]) == 2
    assert "read-only" in capsys.readouterr().err
    locked = study(tmp_path, generations=2, name="lk", storage=f"sqlite:///{database}?timeout=0.2")
    rename(locked, "lk")
    holder = sqlite3.connect(database)
    holder.execute("BEGIN EXCLUSIVE")
    try:
        assert main(["study", "resume", locked]) == 2
        assert "database is locked" in capsys.readouterr().err
    finally:
        holder.rollback()
        holder.close()
    assert rows(database) == before
    damaged = tmp_path / "damaged.sqlite"
    data = bytearray(database.read_bytes())
    data[100:4096] = os.urandom(3996)
    damaged.write_bytes(bytes(data))
    spec_damaged = study(tmp_path, generations=2, name="dm", storage="damaged.sqlite")
    rename(spec_damaged, "dm")
    assert main(["study", "resume", spec_damaged]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and ("malformed" in err or "not a database" in err), err


def test_a_failed_write_stores_no_part_of_its_generation(tmp_path, capsys):
    """A write that fails inside a generation's transaction (here a trigger standing in for a full
    disk) is one line, exit 2, and leaves the generations before it whole and nothing of it."""
    spec = study(tmp_path, generations=2)
    assert main(["study", "run", spec]) == 0
    database = tmp_path / "toy.sqlite"
    with sqlite3.connect(database) as connection:
        connection.execute("CREATE TRIGGER full BEFORE INSERT ON designs WHEN NEW.generation = 2 AND NEW.member = 3 "
                           "BEGIN SELECT RAISE(ABORT, 'database or disk is full'); END")
    connection.close()
    assert main(["study", "resume", spec, "--generations", "4"]) == 2
    err = capsys.readouterr().err
    assert "cannot store generation 2 (nothing of it was stored)" in err and "disk is full" in err
    assert [(g, m) for g, m, _ in rows(database)] == [(g, m) for g in range(2) for m in range(4)]
    with sqlite3.connect(database) as connection:
        assert connection.execute("SELECT generation FROM checkpoints").fetchall() == [(1,)]
        assert connection.execute("SELECT owner FROM studies WHERE name = 'toy'").fetchall() == [(None,)]
    connection.close()


def test_a_pickled_checkpoint_is_never_unpickled_and_the_study_still_resumes(tmp_path, capsys):
    """A study stored by an earlier morphopt (a pickled checkpoint, no optimizer log), here with a
    hostile pickle: `resume` refuses with one line; `resume --trust-checkpoint` rebuilds the optimizer
    from the stored designs (the pickle is never read) and ends like an uninterrupted run. Nothing
    the pickle names is ever written."""
    spec = study(tmp_path, generations=2)
    assert main(["study", "run", spec]) == 0
    database = tmp_path / "toy.sqlite"
    target = tmp_path / "site-packages" / "evil.pth"
    target.parent.mkdir()
    hostile = pickle.dumps(_Write(str(target)))
    with sqlite3.connect(database) as connection:
        connection.execute("UPDATE checkpoints SET state = ?", (hostile,))
        connection.execute("DELETE FROM optimizer_log")
        connection.execute("DROP TABLE studies")  # an earlier morphopt had none
    connection.close()
    digest = hashlib.sha256(database.read_bytes()).hexdigest()
    status, _, err = finish(cli("study", "resume", spec, "--generations", "4", cwd=tmp_path))
    assert status == 2 and "never unpickles" in error_line(err) and "--trust-checkpoint" in error_line(err)
    assert hashlib.sha256(database.read_bytes()).hexdigest() == digest and not target.exists()
    status, out, err = finish(cli("study", "resume", spec, "--generations", "4", "--trust-checkpoint", cwd=tmp_path))
    assert status == 0, err
    assert not target.exists() and sorted(p.name for p in tmp_path.iterdir() if p.suffix == ".pth") == []
    reference = tmp_path / "ref"
    reference.mkdir()
    capsys.readouterr()
    assert main(["study", "run", study(reference, generations=4)]) == 0
    assert out.split("best", 1)[1] == capsys.readouterr().out.split("best", 1)[1]
    assert main(["study", "resume", spec, "--generations", "5"]) == 0  # the log was written back: no flag now


class _Write:
    """Unpickled, this would write a .pth line (the next python run executes it)."""

    def __init__(self, path):
        self.path = path

    def __reduce__(self):
        return eval, (f"open({self.path!r}, 'w').write('import os; os.system(\"touch pwned\")')",)


@pytest.fixture(autouse=True)
def _quiet_cwd(tmp_path, monkeypatch):
    """Run where the study files are (relative family paths), with no leftover lease between tests."""
    monkeypatch.chdir(tmp_path)


# --------------------------------------------------------------------------------------------
# Found by an adversarial review: crafted values, leases across PID namespaces, long locks.


def sql(database, *statements):
    with sqlite3.connect(database) as connection:
        for statement in statements:
            connection.execute(*statement) if isinstance(statement, tuple) else connection.execute(statement)
    connection.close()


def test_crafted_values_in_the_database_are_one_line(tmp_path, capsys):
    """A database may hold any value in any column: a random-generator state out of range, a huge or
    textual generation, settings of the wrong type, terminal escapes. Each is one line, exit 2."""
    from morphopt import checkpoint

    spec = study(tmp_path, generations=2)
    path = pathlib.Path(spec)
    path.write_text(path.read_text().replace("[objective]", '[optimizer]\nname = "optuna"\n[objective]'))
    assert main(["study", "run", spec]) == 0
    database = tmp_path / "toy.sqlite"
    with sqlite3.connect(database) as connection:
        blob = connection.execute("SELECT state FROM checkpoints").fetchone()[0]
    connection.close()
    header, arrays = checkpoint.decode(blob, "x")
    arrays = {**arrays, "optuna.rng0.position": arrays["optuna.rng0.position"].copy()}
    arrays["optuna.rng0.position"][0] = 100000.0  # would read outside the generator's state
    damaged = checkpoint.encode({k: v for k, v in header.items() if k not in ("version", "arrays")}, arrays)
    capsys.readouterr()
    for statements, argv, fragment in (
            ([("UPDATE checkpoints SET state = ?", (damaged,))], ["resume", spec, "--generations", "3"],
             "random generator 0 is damaged"),
            (["UPDATE checkpoints SET generation = 1000000000000"], ["resume", spec, "--generations", "3"],
             "stored generation"),
            (["UPDATE designs SET generation = 'x' WHERE member = 0"], ["show", spec], "damaged"),
            (["UPDATE studies SET settings = '{\"worlds\": \"abc\"}'"], ["show", spec], "stored settings are damaged")):
        backup = database.read_bytes()
        sql(database, *statements)
        assert main(["study", *argv]) == 2, statements
        assert fragment in error_line(capsys.readouterr().err), statements
        database.write_bytes(backup)
    sql(database, "UPDATE designs SET failure = 'jammed \x1b[31mred\x1b[0m' WHERE member = 1")
    assert main(["study", "show", spec]) == 0
    assert "\x1b" not in capsys.readouterr().out


def test_a_lease_is_taken_over_only_when_its_writer_is_gone(tmp_path, capsys):
    """A fresh heartbeat from another PID namespace holds even if its pid means nothing here; an old
    heartbeat does not, even if its pid is alive here (reused); a lock held by another connection
    ends the command in about the URL's timeout, not after retries."""
    spec = study(tmp_path, generations=1)
    assert main(["study", "run", spec]) == 0
    database = tmp_path / "toy.sqlite"
    capsys.readouterr()
    sql(database, ("UPDATE studies SET owner = 'x', pid = 999999999, node = 'elsewhere', heartbeat = ?, since = ?",
                   (time.time(), time.time())))
    assert main(["study", "resume", spec, "--generations", "2"]) == 2
    assert "is being written by pid 999999999" in capsys.readouterr().err
    sql(database, ("UPDATE studies SET pid = ?, heartbeat = ?", (os.getpid(), time.time() - 3600)))
    assert main(["study", "resume", spec, "--generations", "2"]) == 0
    locked = study(tmp_path, generations=3, name="lk", storage=f"sqlite:///{database}?timeout=0.5")
    rename(locked, "lk")
    holder = sqlite3.connect(database)
    holder.execute("BEGIN IMMEDIATE")  # readers go on, writers wait
    start = time.perf_counter()
    try:
        assert main(["study", "resume", locked]) == 2
    finally:
        holder.rollback()
        holder.close()
    assert time.perf_counter() - start < 10.0 and "database is locked" in capsys.readouterr().err


def test_resume_refuses_another_family_source_and_fewer_generations(tmp_path, capsys):
    """The family's source is part of a study: an edited family file is refused by resume, and so is
    --generations below what is stored. One [[objectives]] table is the [objective] table."""
    spec = study(tmp_path, generations=2)
    assert main(["study", "run", spec]) == 0
    capsys.readouterr()
    assert main(["study", "resume", spec, "--generations", "1"]) == 2
    assert "has 2 generations stored" in capsys.readouterr().err
    family = tmp_path / "toy_family.py"
    family.write_text(family.read_text() + "\n# edited\n")
    assert main(["study", "resume", spec, "--generations", "3"]) == 2
    assert "is not the source study 'toy' was run with" in capsys.readouterr().err
    path = pathlib.Path(spec)
    one = path.read_text().replace("[objective]", "[[objectives]]").replace('"maximize"', '"minimize"')
    (tmp_path / "one.toml").write_text(one)
    from morphopt.study_spec import load_study_spec

    single = load_study_spec(tmp_path / "one.toml")
    assert (single.metric, single.direction) == ("tip_step_height", "minimize") and not single.multi_objective


def test_fresh_runs_are_never_mixed_in_an_optuna_export(tmp_path, capsys):
    """Exporting a study, starting it over with --fresh and exporting again into the same Optuna
    study is refused (the designs at the same generation and member differ)."""
    spec = study(tmp_path, generations=1)
    url = f"sqlite:///{tmp_path / 'optuna.db'}"
    assert main(["study", "run", spec]) == 0
    assert main(["study", "export", spec, "--optuna-storage", url]) == 0
    path = pathlib.Path(spec)
    path.write_text(path.read_text().replace("seed = 5", "seed = 6"))
    assert main(["study", "run", spec, "--fresh"]) == 0
    capsys.readouterr()
    assert main(["study", "export", spec, "--optuna-storage", url]) == 2
    assert "holds another run of this study" in capsys.readouterr().err


def test_an_archive_name_fits_the_study_columns(tmp_path):
    from morphopt.storage import StudyStorage

    storage = StudyStorage(f"sqlite:///{tmp_path / 'x.sqlite'}", "n" * 200)
    assert len(storage.archive_name()) <= 200
