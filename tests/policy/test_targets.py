import pytest
import torch

from uevavd.policy import targets as T


def test_dueling_subtracts_mean_advantage():
    v = torch.tensor([[1.0], [2.0]])
    a = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 3.0]])
    q = T.dueling(v, a)
    assert torch.allclose(q, torch.tensor([[0.0, 1.0, 2.0], [1.0, 1.0, 4.0]]))
    assert torch.allclose(q.mean(-1, keepdim=True), v)


def test_td_target_does_not_bootstrap_past_done():
    r = torch.tensor([0.5, -0.1])
    done = torch.tensor([True, False])
    nxt = torch.tensor([[10.0, 10.0], [1.0, 3.0]])
    y = T.td_target(r, done, nxt, 0.9)
    assert torch.allclose(y, torch.tensor([[0.5, 0.5], [-0.1 + 0.9, -0.1 + 2.7]]))


def test_branch_bootstrap_mean_and_indep():
    qt = torch.tensor([[0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0]])
    qr = torch.tensor([[10.0, 20.0, 30.0, 40.0]])
    a_t, a_r = torch.tensor([2]), torch.tensor([3])
    assert torch.allclose(T.branch_bootstrap(qt, qr, a_t, a_r, "mean"), torch.tensor([[21.0, 21.0]]))
    assert torch.allclose(T.branch_bootstrap(qt, qr, a_t, a_r, "indep"), torch.tensor([[2.0, 40.0]]))
    # a greedy stop ignores the range: both branches use the type branch's value
    stop = torch.tensor([T.STOP])
    assert torch.allclose(T.branch_bootstrap(qt, qr, stop, a_r, "mean"), torch.tensor([[6.0, 6.0]]))
    with pytest.raises(ValueError, match="td_target"):
        T.branch_bootstrap(qt, qr, a_t, a_r, "max")


def test_masked_greedy_avoids_clamped_moves():
    q_type = torch.tensor([[9.0, 0, 0, 0, 0, 0, 1.0]])
    q_range = torch.tensor([[0.0, 0.0, 0.0, 5.0]])
    mask = torch.ones(1, 7, 4, dtype=torch.bool)
    mask[0, 0] = False  # forward would be clamped at every range
    mask[0, 6, :] = True
    mask[0, 1:6, 3] = False  # range 4 clamped for the other moves
    a_type, a_range = T.branch_greedy(q_type, q_range, mask)
    assert int(a_type) == 6  # stop beats the remaining moves
    a_type, a_range = T.branch_greedy(torch.tensor([[9.0, 8.0, 0, 0, 0, 0, 1.0]]), q_range, mask)
    assert (int(a_type), int(a_range)) == (1, 0)
    flat = torch.zeros(1, 28)
    flat[0, 3] = 9.0  # forward, range 4: masked
    flat[0, 5] = 8.0  # backward, range 2
    assert tuple(int(x) for x in T.joint_greedy(flat, mask, 4)) == (1, 1)


def test_range_branch_gets_no_loss_on_stop():
    w = T.branch_weights(torch.tensor([0, 6]))
    assert w.tolist() == [[1.0, 1.0], [1.0, 0.0]]


def test_joint_head_counts_stop_once():
    """Stop ignores its range: the joint head reads only stop's range-0 entry, when acting
    greedily (with or without a mask) and when reading the Q of a taken stop."""
    q = torch.zeros(2, 28)
    q[:, T.STOP * 4 + 3] = 9.0  # a never-read copy of stop
    q[:, T.STOP * 4 + 0] = 1.0
    q[1, 5] = 2.0  # backward, range 2
    mask = torch.ones(2, 7, 4, dtype=torch.bool)
    for m in (mask, None):
        a_type, a_range = T.joint_greedy(q, m, 4)
        assert a_type.tolist() == [T.STOP, 1] and a_range.tolist() == [0, 1]
    idx = T.joint_index(torch.tensor([T.STOP, T.STOP, 2]), torch.tensor([0, 3, 3]), 4)
    assert idx.tolist() == [24, 24, 11]
