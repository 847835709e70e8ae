"""eqa.grid: world <-> cell conversion, bounds."""

from __future__ import annotations

import math

import numpy as np

from eqa import grid
from eqa.messages import GridSpec

ORIGIN = (-3.25, 1.5)
RES = 0.1


def test_cell_of_floors_and_matches_the_scalar_form() -> None:
    rng = np.random.default_rng(0)
    x = rng.uniform(-10, 10, 1000)
    y = rng.uniform(-10, 10, 1000)
    row, col = grid.cell_of(x, y, ORIGIN, RES)
    assert row.dtype == np.int64 and col.dtype == np.int64
    # the formula every module wrote by hand, bit for bit
    assert np.array_equal(col, np.floor((x - ORIGIN[0]) / RES).astype(np.int64))
    assert np.array_equal(row, np.floor((y - ORIGIN[1]) / RES).astype(np.int64))
    for k in range(0, 1000, 37):
        assert grid.cell_of_point(float(x[k]), float(y[k]), ORIGIN, RES) == (row[k], col[k])
    # a point just below the origin is in cell -1 (floor, not truncation)
    assert grid.cell_of_point(ORIGIN[0] - 1e-9, ORIGIN[1] - 1e-9, ORIGIN, RES) == (-1, -1)
    assert grid.cell_of_point(*ORIGIN, ORIGIN, RES) == (0, 0)


def test_cell_centre_round_trip_and_types() -> None:
    rr, cc = np.mgrid[-5:40, -5:30]
    xs, ys = grid.cell_center(rr, cc, ORIGIN, RES)
    assert np.array_equal(xs, ORIGIN[0] + (cc + 0.5) * RES) and np.array_equal(ys, ORIGIN[1] + (rr + 0.5) * RES)
    r2, c2 = grid.cell_of(xs, ys, ORIGIN, RES)
    assert np.array_equal(r2, rr) and np.array_equal(c2, cc)
    x, y = grid.cell_center(3, 4, ORIGIN, RES)
    assert type(x) is float and type(y) is float  # Python scalars stay Python scalars (message fields)
    fr, fc = grid.fractional_cell(x, y, ORIGIN, RES)
    assert math.isclose(fr, 3.5) and math.isclose(fc, 4.5)
    assert grid.world_of(fr, fc, ORIGIN, RES) == (ORIGIN[0] + fc * RES, ORIGIN[1] + fr * RES)
    # rows and columns of different lengths (a window of a layer)
    xs, ys = grid.cell_center(np.arange(2, 5), np.arange(0, 7), ORIGIN, RES)
    assert xs.shape == (7,) and ys.shape == (3,)


def test_inside_bounds_contains() -> None:
    row = np.array([-1, 0, 9, 10, 5])
    col = np.array([0, -1, 4, 0, 19])
    assert grid.inside(row, col, (10, 20)).tolist() == [False, False, True, False, True]
    assert grid.inside(0, 0, (1, 1)) and not grid.inside(1, 0, (1, 1))
    spec = GridSpec(origin_x=ORIGIN[0], origin_y=ORIGIN[1], resolution=RES, rows=10, cols=20)
    assert grid.origin_of(spec) == ORIGIN
    x0, y0, x1, y1 = grid.bounds(spec)
    assert (x0, y0) == ORIGIN and math.isclose(x1, ORIGIN[0] + 2.0) and math.isclose(y1, ORIGIN[1] + 1.0)
    assert grid.contains(spec, *ORIGIN) and not grid.contains(spec, x1, y0) and not grid.contains(spec, x0, y1)
    assert not grid.contains(spec, float("nan"), y0)
