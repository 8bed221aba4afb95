"""Path metrics against analytic curves, and their convergence with the sampling."""

import numpy as np
import pytest

from morphopt.evaluate import evaluate_kinematic
from morphopt.families import load_family
from morphopt.metrics import gait_metrics, gait_metrics_batch, path_error, resample_closed, stride_and_step_height, \
    torque_stats


def circle(radius, count, phase=0.0, center=(0.0, 0.0), direction=1):
    t = phase + direction * 2 * np.pi * np.arange(count) / count
    return np.stack([center[0] + radius * np.cos(t), center[1] + radius * np.sin(t)], axis=1)


def test_path_error_ignores_phase_direction_and_speed():
    """The same circle started elsewhere, run backwards, or sampled unevenly has ~zero error."""
    target = circle(0.1, 200)
    uneven = circle(0.1, 400)[np.sort(np.random.default_rng(0).choice(400, 150, replace=False))]
    for path in (circle(0.1, 300, phase=1.3), circle(0.1, 300, direction=-1), uneven):
        assert path_error(path, target, samples=256) < 2e-4


def test_path_error_of_concentric_circles_is_their_radius_gap():
    """Concentric circles of radii 0.10 and 0.13 are 0.03 apart everywhere (RMS 0.03)."""
    assert abs(path_error(circle(0.13, 360), circle(0.10, 360), samples=360) - 0.03) < 1e-4


def test_infeasible_path_has_infinite_error():
    """NaN in a path (an infeasible design) gives inf."""
    path = circle(0.1, 50)
    path[3] = np.nan
    assert path_error(path, circle(0.1, 50)) == np.inf


def test_stride_and_step_height_of_a_d_shaped_path():
    """A flat-bottomed D path: stride = length of the flat part (the smooth curve through the
    samples overshoots its corners by a little), step height = the arch's height, 0.1, found
    between the samples (the highest sample is 0.09999)."""
    flat = np.stack([np.linspace(0.3, -0.3, 100), np.zeros(100)], axis=1)
    angles = np.linspace(np.pi, 0.0, 100)
    arch = np.stack([0.3 * np.cos(angles), 0.1 * np.sin(angles)], axis=1)
    stride, height = stride_and_step_height(np.vstack([flat, arch]))
    assert abs(stride - 0.6) < 0.01 and abs(height - 0.1) < 1e-8 < abs(0.1 * np.sin(angles).max() - 0.1)


@pytest.mark.parametrize("samples", [36, 90, 360, 3600])
def test_gait_metrics_of_an_ellipse_are_analytic(samples):
    """An ellipse x = a cos t, y = b sin t at any phase: step height 2b; the stance (y within 2 % of
    2b above -b) is |sin t| >= 0.96, so stride = 2a sqrt(1 - 0.96^2) = 0.56 a; full stride 2a. The
    nearest-sample rule was 38 % short at 36 samples and 1.6 % at 360."""
    a, b = 0.05, 0.02
    tolerance = {36: 3e-4, 90: 3e-6, 360: 1e-7, 3600: 1e-10}[samples]
    for phase in (0.0, 0.3, 1.1, 2.0):
        t = phase + 2.0 * np.pi * np.arange(samples) / samples
        path = np.stack([0.2 + a * np.cos(t), -0.1 + b * np.sin(t)], axis=1)
        stride, full, height = gait_metrics(path)
        assert abs(stride / (0.56 * a) - 1.0) < tolerance, (phase, stride)
        assert abs(full / (2.0 * a) - 1.0) < tolerance and abs(height / (2.0 * b) - 1.0) < tolerance
        backwards = gait_metrics(path[::-1])
        assert np.allclose(backwards, (stride, full, height), rtol=1e-12, atol=0.0)


def test_open_runs_and_batches_give_the_closed_numbers():
    """A whole cycle read as an open run of records (a rollout's last turn) whose ends do not fall
    in the stance gives the closed path's numbers; gait_metrics_batch of paths in windows that start
    at different records gives each path's own numbers; a NaN makes all three NaN."""
    t = 0.7 + 2.0 * np.pi * np.arange(200) / 200
    path = np.stack([0.05 * np.cos(t), 0.02 * np.sin(t)], axis=1)
    assert np.allclose(gait_metrics(path, closed=False), gait_metrics(path), rtol=1e-9, atol=0.0)
    u = 2.0 * np.pi * np.arange(220) / 190  # 1.16 turns of another ellipse
    other = np.stack([0.03 * np.cos(u), 0.01 * np.sin(u) + 0.004 * np.cos(3 * u)], axis=1)
    columns = np.stack([np.vstack([np.full((50, 2), 7.0), path]), np.vstack([np.full((30, 2), -7.0), other])], axis=1)
    got = np.array(gait_metrics_batch(columns[..., 0], columns[..., 1], [50, 30], closed=False))
    for column, alone in enumerate((path, other)):
        assert np.allclose(got[:, column], gait_metrics(alone, closed=False), rtol=1e-12, atol=0.0)
    broken = path.copy()
    broken[17, 1] = np.nan
    assert all(np.isnan(v) for v in gait_metrics(broken))


@pytest.mark.parametrize("name", ["jansen_leg", "klann_leg", "four_bar", "watt_sixbar"])
def test_stride_converges_with_the_samples(name):
    """At a study's default 360 samples the default design's stride, full stride and step height are
    within 0.1 % (in fact 0.002 %) of their values at 36,000 samples, the limit, for every linkage
    family; Jansen's leg at his numbers: a 49.29 mm flat stance of a 67.91 mm foot travel (the
    nearest-sample rule gave 47.60 mm at 90 samples, 48.66 at 360, 49.24 at 3,600, 49.29 at 36,000)."""
    family = load_family(name)
    point = next(iter(family.generate(family.space.default()).points))
    default = [family.space.default()]
    values = {samples: evaluate_kinematic(family, default, samples=samples, keep_paths=False).metrics[0]
              for samples in (90, 360, 36000)}
    for metric in ("stride", "stride_full", "step_height"):
        key = f"{point}_{metric}"
        limit = values[36000][key]
        assert abs(values[360][key] / limit - 1.0) < 1e-3 * 0.02, (key, values[360][key], limit)
        assert abs(values[90][key] / limit - 1.0) < 1e-3, (key, values[90][key], limit)
    if name == "jansen_leg":
        assert abs(values[360]["foot_stride"] - 0.049294) < 1e-6
        assert abs(values[360]["foot_stride_full"] - 0.067908) < 1e-6


def test_resample_keeps_points_on_the_curve_and_torque_stats():
    """Arc-length resampling of a square stays on its edges; torque stats of a sine are 1 and 1/sqrt 2."""
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    points = resample_closed(square, 40)
    on_edge = np.minimum(np.minimum(np.abs(points[:, 0]), np.abs(points[:, 0] - 1)),
                         np.minimum(np.abs(points[:, 1]), np.abs(points[:, 1] - 1)))
    assert on_edge.max() < 1e-12 and abs(np.linalg.norm(points[1] - points[0]) - 0.1) < 1e-12
    peak, rms = torque_stats(np.sin(np.linspace(0, 2 * np.pi, 10001)))
    assert abs(peak - 1.0) < 1e-6 and abs(rms - 1 / np.sqrt(2)) < 1e-3
