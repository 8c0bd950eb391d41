"""The pooled map coarse GICP pairs with (EgoMap.pooled): each cell the mean of its voxels, summed exactly, so that
neither the voxels' order nor a turn of the frame by 90 degrees changes a bit."""

import numpy as np

from occvo_core.grid import NUM_CLASSES
from occvo_core.registration.kernels.map_window import pool_voxels

ORIGIN, DIMS, PAD = np.array([-5, -5, -1]), np.array([10, 10, 4]), 2


def _voxels(n=4000, seed=3):
    rng = np.random.default_rng(seed)
    pos = np.column_stack([rng.uniform(-6, 6, n), rng.uniform(-6, 6, n), rng.uniform(-1.5, 3.5, n)])
    a = rng.normal(size=(n, 3, 3))
    return pos, a @ a.transpose(0, 2, 1), rng.integers(0, NUM_CLASSES - 1, n).astype(np.uint8)


def _pool(pos, cov, labels):
    """(positions, covariances, labels, weights) of the cells, ordered by position (the cells' numbers follow the
    points' order)."""
    out = pool_voxels(
        pos, cov, labels, np.ones(len(pos), bool), np.zeros(0), np.zeros((0, NUM_CLASSES), np.int32), 1.2, ORIGIN,
        DIMS, NUM_CLASSES, PAD,
    )  # fmt: skip
    order = np.lexsort(out[0].T[::-1])
    return out[0][order], out[1][order], out[2][order], out[4][order]


def test_a_cell_is_the_mean_of_its_voxels():
    pos, cov, labels = _voxels()
    cells = np.floor(pos / 1.2).astype(np.int64)
    inside = np.all((cells >= ORIGIN) & (cells < ORIGIN + DIMS), axis=1)
    mean_pos, mean_cov, label, weight = _pool(pos, cov, labels)
    assert weight.sum() == inside.sum() and len(mean_pos) == len(np.unique(cells[inside], axis=0))
    for c in (0, len(mean_pos) // 2, len(mean_pos) - 1):
        members = inside & np.all(cells == np.floor(mean_pos[c] / 1.2).astype(np.int64), axis=1)
        np.testing.assert_allclose(mean_pos[c], pos[members].mean(axis=0), rtol=0, atol=1e-9)
        np.testing.assert_allclose(mean_cov[c], cov[members].mean(axis=0), rtol=0, atol=1e-9)
        assert label[c] == np.argmax(np.bincount(labels[members], minlength=NUM_CLASSES))


def test_the_voxels_order_changes_no_bit():
    pos, cov, labels = _voxels()
    shuffled = np.random.default_rng(7).permutation(len(pos))
    for a, b in zip(_pool(pos, cov, labels), _pool(pos[shuffled], cov[shuffled], labels[shuffled])):
        assert np.array_equal(a, b)


def test_a_quarter_turn_turns_the_cells_bit_for_bit():
    pos, cov, labels = _voxels()
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # (x, y) -> (-y, x): exact
    turned_pos = np.column_stack([-pos[:, 1], pos[:, 0], pos[:, 2]])
    turned_cov = turn @ cov @ turn.T  # entries moved and negated only
    mean_pos, mean_cov, label, weight = _pool(pos, cov, labels)
    t_pos, t_cov, t_label, t_weight = _pool(turned_pos, turned_cov, labels)
    back = np.lexsort(np.column_stack([-mean_pos[:, 1], mean_pos[:, 0], mean_pos[:, 2]]).T[::-1])
    assert np.array_equal(t_pos, np.column_stack([-mean_pos[:, 1], mean_pos[:, 0], mean_pos[:, 2]])[back])
    assert np.array_equal(t_cov, (turn @ mean_cov @ turn.T)[back])
    assert np.array_equal(t_label, label[back]) and np.array_equal(t_weight, weight[back])
