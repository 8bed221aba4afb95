"""The README's Python example runs as printed and shows what it promises."""

import pathlib
import re


def test_readme_engine_example_runs(capsys):
    """The engine quick start plans a 64-world mixed batch in two groups (the four-bars in tree
    coordinates; the arms maximal, their motors starting past their effort limit, which only the
    maximal plan enforces), keeps its joints closed, reports every world healthy and prints what
    it promises."""
    text = (pathlib.Path(__file__).parents[1] / "README.md").read_text()
    code = re.search(r"## The engine in 20 lines\s*```python\n(.*?)```", text, re.S).group(1)
    namespace = {}
    exec(compile(code, "README.md", "exec"), namespace)
    trace = namespace["trace"]
    assert trace.points.shape == (101, 64, 1, 3)
    assert trace.violation_linear.max() < 1e-5
    assert trace.health.ok.all()
    out = capsys.readouterr().out
    assert "(101, 64, 1, 3)" in out
    assert "plan for 64 worlds on cpu: 2 groups" in out
    assert "group of 32 worlds: plan for 32 worlds on cpu: tree coordinates" in out
    assert "joint 'motor': its drive starts past its effort limit" in out
