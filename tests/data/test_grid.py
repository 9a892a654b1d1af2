import numpy as np
import pytest

from uevavd.data import grid


def test_605_unique_views_in_index_order():
    views = np.arange(grid.N_VIEWS)
    coords = grid.view_coords(views)
    assert grid.N_VIEWS == 605
    assert len({tuple(c) for c in coords}) == 605
    # index = (ix * 11 + iy) * 5 + iz, x outermost, z innermost
    assert tuple(grid.view_coords(0)) == (-50, -50, 60)
    assert tuple(grid.view_coords(1)) == (-50, -50, 70)
    assert tuple(grid.view_coords(5)) == (-50, -40, 60)
    assert tuple(grid.view_coords(55)) == (-40, -50, 60)
    assert tuple(grid.view_coords(604)) == (50, 50, 100)


def test_index_round_trip():
    for v in range(grid.N_VIEWS):
        x, y, z = grid.view_coords(v)
        assert grid.coords_to_view(x, y, z) == v
        assert grid.view_index(*grid.grid_indices(v)) == v


@pytest.mark.parametrize("bad", [(-60, 0, 60), (0, 0, 55), (5, 0, 60), (0, 0, 110)])
def test_off_grid_coordinates_are_refused(bad):
    with pytest.raises(ValueError, match="not a grid coordinate"):
        grid.coords_to_view(*bad)


def test_view_index_off_grid():
    with pytest.raises(ValueError, match="off the grid"):
        grid.view_coords(605)
    with pytest.raises(ValueError, match="iz=5"):
        grid.view_index(0, 0, 5)


DIRS = {0: (0, 1, 0), 1: (0, -1, 0), 2: (-1, 0, 0), 3: (1, 0, 0), 4: (0, 0, -1), 5: (0, 0, 1)}


def test_moves_follow_directions_and_clamp_at_every_edge():
    t = grid.transitions(4)
    for v in range(grid.N_VIEWS):
        pos = np.array(grid.grid_indices(v))
        for a_type, d in DIRS.items():
            for r in range(4):
                want = pos + np.array(d) * (r + 1)
                got = np.clip(want, 0, [10, 10, 4])
                nv, steps, metres, clamped = grid.move(v, a_type, r)
                assert nv == grid.view_index(*got)
                assert clamped == bool((want != got).any())
                assert steps == int(np.abs(got - pos).sum())
                assert metres == 10.0 * steps
                # the mask agrees with clamping
                assert t.mask[v, a_type, r] == (not clamped)
        for r in range(4):  # stop stays, flies nothing, is always allowed
            assert grid.move(v, grid.STOP, r) == (v, 0, 0.0, False)
            assert t.mask[v, grid.STOP, r]


def test_clamping_examples():
    corner = grid.coords_to_view(50, 50, 100)
    # right by 4 from x=50: clamped, nothing flown
    assert grid.move(corner, 3, 3) == (corner, 0, 0.0, True)
    # left by 4 from x=50: to x=10, 40 m
    nv, steps, metres, clamped = grid.move(corner, 2, 3)
    assert tuple(grid.view_coords(nv)) == (10, 50, 100) and steps == 4 and metres == 40 and not clamped
    # down by 4 from z=70: clamped at z=60 after 10 m
    v = grid.coords_to_view(0, 0, 70)
    nv, steps, metres, clamped = grid.move(v, 4, 3)
    assert tuple(grid.view_coords(nv)) == (0, 0, 60) and steps == 1 and metres == 10 and clamped
    mask = grid.action_mask(v)
    assert mask.shape == (7, 4) and mask[4].tolist() == [True, False, False, False]


def test_bad_actions_are_named():
    with pytest.raises(ValueError, match="action type 7"):
        grid.move(0, 7, 0)
    with pytest.raises(ValueError, match="range index 4"):
        grid.move(0, 0, 4)


def test_flat_action_round_trip():
    seen = {grid.flat_action(t, r) for t in range(7) for r in range(4)}
    assert seen == set(range(28))
    for a in range(28):
        assert grid.flat_action(*grid.unflat_action(a)) == a
