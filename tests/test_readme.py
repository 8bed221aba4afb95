"""The README's Python example runs as printed and shows what it promises."""

import pathlib
import re


def test_readme_engine_example_runs(capsys):
    """The engine quick start plans a 64-world batch of arms and four-bars in grounded coordinates
    (one angle per world; the arms' motors start past their effort limit, which the grounded plan
    enforces), keeps its joints closed, reports every world healthy and prints what it promises."""
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
    assert "plan for 64 worlds on cpu: grounded coordinates" in out
    torque = trace.drive_torque[1:, :32, 0]
    assert abs(torque).max() <= 2.0 + 1e-4 and abs(torque[0]).min() > 1.99  # the motors at their limit at first
