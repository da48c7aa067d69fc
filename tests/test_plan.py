"""Mesh, passes, approach directions, timing (Eq. 4) and sensor interpolation."""

import numpy as np
import pytest

from mtbudget.errors import ConfigError
from mtbudget.plan import Plan, Sensor, build_plan, mesh, verification_time


def test_paper_mesh_has_75_points_x_fastest():
    pts = mesh({"x": (800, 1200), "y": (100, 500), "z": (200, 400)}, 100)
    assert pts.shape == (75, 3)
    assert np.array_equal(pts[:5, 0], [800, 900, 1000, 1100, 1200])
    assert set(pts[:, 2]) == {200, 300, 400}
    with pytest.raises(ConfigError):
        mesh({"x": (800, 1250), "y": (100, 500), "z": (200, 400)}, 100)


def test_timing_is_equation_4_and_passes_alternate():
    pts = mesh({"x": (0, 300), "y": (0, 100), "z": (0, 0)}, 100)
    feed, ts = 10.0, 5.0
    plan = build_plan(pts, [[0, 0, 0]], runs=2, feed=feed, stop_time=ts, tool_change_time=0)
    n = len(pts)
    path = np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))
    assert plan.time[n - 1] == pytest.approx(verification_time(path, feed, ts, n))
    assert np.array_equal(plan.point[n:], plan.point[:n][::-1])
    assert np.array_equal(plan.run, [1] * n + [2] * n)


def test_approach_direction_is_the_sign_of_the_last_move():
    pts = np.array([[0, 0, 0], [100, 0, 0], [100, 100, 0], [0, 100, 0], [0, 100, 50]], float)
    plan = build_plan(pts, [[0, 0, 0]], runs=1, start_direction=1.0)
    assert plan.direction[:, 0].tolist() == [1, 1, 1, -1, -1]
    assert plan.direction[:, 1].tolist() == [1, 1, 1, 1, 1]
    assert plan.direction[:, 2].tolist() == [1, 1, 1, 1, 1]


def test_axis_temperature_interpolates_linearly_between_sensors():
    nominal = np.array([[800.0, 0, 0], [1000.0, 0, 0], [1200.0, 0, 0], [1300.0, 0, 0]])
    plan = Plan(np.arange(4), np.ones(4, int), np.arange(4.0), nominal, np.ones((4, 3)), np.zeros((4, 3)),
                temperature={"a": np.full(4, 294.0), "b": np.full(4, 296.0), "c": np.full(4, 299.0)},
                sensors=[Sensor("a", "x axis", 800.0), Sensor("b", "x axis", 1200.0), Sensor("c", "y axis")])
    assert np.allclose(plan.axis_temperature("x"), [294.0, 295.0, 296.0, 296.0])
    assert np.allclose(plan.axis_temperature("y"), 299.0)
    assert np.allclose(plan.axis_temperature("z", reference=293.15), 293.15)
