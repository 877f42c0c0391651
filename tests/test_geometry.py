"""The one geometry module: a tag's position, a distance in any layout, its Jacobian."""

from __future__ import annotations

import math

import numpy as np
import pytest

from relloc import geometry


def test_a_tag_turns_with_its_robot() -> None:
    arm = (0.3, 0.0)
    assert np.allclose(geometry.tag_position((1.0, 2.0), 0.0, arm), (1.3, 2.0))
    assert np.allclose(geometry.tag_position((1.0, 2.0), math.pi / 2, arm), (1.0, 2.3))
    # many robots at once, and a 3D arm: yaw turns x and y, z is carried
    many = geometry.tag_position(np.zeros((2, 3)), np.array([0.0, math.pi]), (0.3, 0.1, 0.2))
    assert np.allclose(many, [[0.3, 0.1, 0.2], [-0.3, -0.1, 0.2]])


def test_a_distance_is_the_same_bits_in_either_layout() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(50, 2)), rng.normal(size=(50, 2))
    last = geometry.distance(a, b)
    first = geometry.norm((a - b).T.copy(), axis=0, overwrite=True)
    diff = a - b
    assert np.array_equal(last, first)
    assert np.array_equal(last, np.sqrt(diff[:, 0] * diff[:, 0] + diff[:, 1] * diff[:, 1]))
    assert np.allclose(last, np.hypot(diff[:, 0], diff[:, 1]), rtol=1e-15)
    # the input is left alone unless asked
    before = diff.copy()
    geometry.norm(diff)
    assert np.array_equal(diff, before)


def test_the_direction_is_the_range_jacobian() -> None:
    a, b = np.array([1.0, 2.0]), np.array([-0.5, 0.7])
    dist, u = geometry.direction(a - b)
    step = 1e-6
    numeric = [
        (geometry.distance(a + step * e, b) - geometry.distance(a - step * e, b)) / (2 * step)
        for e in np.eye(2)
    ]
    assert dist == pytest.approx(math.dist(a, b))
    assert np.allclose(u, numeric, atol=1e-8)


def test_coinciding_points_have_no_direction_but_a_fallback() -> None:
    same = np.zeros((1, 2))
    _, short = geometry.direction(same)
    assert np.array_equal(short, [[0.0, 0.0]])
    _, fallback = geometry.direction(same, fallback=(1.0, 0.0))
    assert np.array_equal(fallback, [[1.0, 0.0]])
