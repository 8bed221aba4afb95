"""Path metrics against analytic curves."""

import numpy as np

from morphopt.metrics import path_error, resample_closed, stride_and_step_height, torque_stats


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
    """A flat-bottomed D path: stride = length of the flat part, step height = arch height."""
    flat = np.stack([np.linspace(0.3, -0.3, 100), np.zeros(100)], axis=1)
    angles = np.linspace(np.pi, 0.0, 100)
    arch = np.stack([0.3 * np.cos(angles), 0.1 * np.sin(angles)], axis=1)
    stride, height = stride_and_step_height(np.vstack([flat, arch]))
    assert abs(stride - 0.6) < 0.01 and abs(height - 0.1 * np.sin(angles).max()) < 1e-12


def test_resample_keeps_points_on_the_curve_and_torque_stats():
    """Arc-length resampling of a square stays on its edges; torque stats of a sine are 1 and 1/sqrt 2."""
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    points = resample_closed(square, 40)
    on_edge = np.minimum(np.minimum(np.abs(points[:, 0]), np.abs(points[:, 0] - 1)),
                         np.minimum(np.abs(points[:, 1]), np.abs(points[:, 1] - 1)))
    assert on_edge.max() < 1e-12 and abs(np.linalg.norm(points[1] - points[0]) - 0.1) < 1e-12
    peak, rms = torque_stats(np.sin(np.linspace(0, 2 * np.pi, 10001)))
    assert abs(peak - 1.0) < 1e-6 and abs(rms - 1 / np.sqrt(2)) < 1e-3
