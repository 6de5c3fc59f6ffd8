"""Poincare-ball operations against closed forms, and HGCN layers staying inside the ball."""

import math

import numpy as np
import pytest
import torch

from orbslam_hgcn.config import HgcnTrainConfig
from orbslam_hgcn.vocabulary.training import hyperbolic as hyp
from orbslam_hgcn.vocabulary.training.hgcn import HGCN, HGCNLayer, sparse_tensor

C_VALUES = [0.3, 1.0, 2.5]


def _ball_points(n, d, c, seed, max_frac=0.9):
    g = torch.Generator().manual_seed(seed)
    u = torch.randn(n, d, generator=g, dtype=torch.float64)
    r = torch.rand(n, 1, generator=g, dtype=torch.float64) * max_frac / math.sqrt(c)
    return u / u.norm(dim=1, keepdim=True) * r


@pytest.mark.parametrize("c", C_VALUES)
def test_mobius_addition_closed_forms(c):
    # 1-D: x (+)_c y = (x + y) / (1 + c x y)
    x = torch.tensor([[0.3], [-0.5], [0.1]], dtype=torch.float64) / math.sqrt(c)
    y = torch.tensor([[0.4], [0.2], [-0.6]], dtype=torch.float64) / math.sqrt(c)
    torch.testing.assert_close(hyp.mobius_add(x, y, c), (x + y) / (1 + c * x * y))
    # Identities in 5-D: x (+) 0 = x, 0 (+) y = y, (-x) (+) x = 0, (-x) (+) (x (+) y) = y.
    a, b = _ball_points(20, 5, c, 1), _ball_points(20, 5, c, 2)
    zero = torch.zeros_like(a)
    torch.testing.assert_close(hyp.mobius_add(a, zero, c), a)
    torch.testing.assert_close(hyp.mobius_add(zero, b, c), b)
    torch.testing.assert_close(hyp.mobius_add(-a, a, c), zero, atol=1e-12, rtol=0)
    torch.testing.assert_close(hyp.mobius_add(-a, hyp.mobius_add(a, b, c), c), b, atol=1e-10, rtol=0)
    # The result stays in the ball.
    assert (c * hyp.mobius_add(a, b, c).pow(2).sum(-1) < 1).all()


@pytest.mark.parametrize("c", C_VALUES)
def test_exp_log_maps_invert_and_match_closed_forms(c):
    g = torch.Generator().manual_seed(3)
    u = torch.randn(30, 4, generator=g, dtype=torch.float64) * 0.7
    y = hyp.expmap0(u, c)
    torch.testing.assert_close(hyp.logmap0(y, c), u)
    # |exp_0(u)| = tanh(sqrt(c)|u|) / sqrt(c) and d(0, exp_0(u)) = lambda_0 |u| = 2 |u|.
    un = u.norm(dim=-1)
    torch.testing.assert_close(y.norm(dim=-1), torch.tanh(math.sqrt(c) * un) / math.sqrt(c))
    torch.testing.assert_close(hyp.dist(torch.zeros_like(y), y, c), 2 * un)
    # At a point x: log_x(exp_x(v)) = v and d(x, exp_x(v)) = lambda_x |v|.
    x = _ball_points(30, 4, c, 4, max_frac=0.7)
    v = torch.randn(30, 4, generator=g, dtype=torch.float64) * 0.3
    z = hyp.expmap(x, v, c)
    torch.testing.assert_close(hyp.logmap(x, z, c), v, atol=1e-9, rtol=1e-7)
    torch.testing.assert_close(hyp.dist(x, z, c), (hyp.lambda_x(x, c) * v.norm(dim=-1, keepdim=True)).squeeze(-1))


@pytest.mark.parametrize("c", C_VALUES)
def test_distances_agree_with_closed_forms(c):
    # 1-D ball: d(x, y) = 2/sqrt(c) |artanh(sqrt(c) y) - artanh(sqrt(c) x)|.
    x = torch.tensor([[0.1], [-0.7], [0.5]], dtype=torch.float64) / math.sqrt(c)
    y = torch.tensor([[0.6], [0.3], [-0.2]], dtype=torch.float64) / math.sqrt(c)
    sc = math.sqrt(c)
    expected = 2 / sc * (torch.atanh(sc * y) - torch.atanh(sc * x)).abs().squeeze(-1)
    torch.testing.assert_close(hyp.dist(x, y, c), expected)
    # n-D: the Mobius form equals arcosh(1 + 2c|x-y|^2 / ((1-c|x|^2)(1-c|y|^2))) / sqrt(c).
    a, b = _ball_points(25, 6, c, 5), _ball_points(25, 6, c, 6)
    arg = 1 + 2 * c * (a - b).pow(2).sum(-1) / ((1 - c * a.pow(2).sum(-1)) * (1 - c * b.pow(2).sum(-1)))
    torch.testing.assert_close(hyp.dist(a, b, c), torch.acosh(arg) / sc)
    # The pairwise squared-distance matrix used by the decoder.
    d2 = hyp.sq_dist_matrix(a, b[:7], c)
    torch.testing.assert_close(d2, hyp.dist(a[:, None, :], b[None, :7, :], c).pow(2), atol=1e-9, rtol=1e-7)
    torch.testing.assert_close(hyp.sq_dist_matrix(a, a, c).diagonal(), torch.zeros(25, dtype=torch.float64),
                               atol=1e-5, rtol=0)
    # Triangle inequality.
    e = _ball_points(25, 6, c, 7)
    assert (hyp.dist(a, e, c) <= hyp.dist(a, b, c) + hyp.dist(b, e, c) + 1e-9).all()


@pytest.mark.parametrize("c", C_VALUES)
def test_mobius_matrix_and_scalar_products(c):
    x = _ball_points(10, 3, c, 8)
    torch.testing.assert_close(hyp.mobius_matvec(torch.eye(3, dtype=torch.float64), x, c), x)
    # r I acts as the Mobius scalar product, and 2 (x) x = x (+) x.
    torch.testing.assert_close(hyp.mobius_matvec(2 * torch.eye(3, dtype=torch.float64), x, c),
                               hyp.mobius_scalar_mul(2.0, x, c))
    torch.testing.assert_close(hyp.mobius_scalar_mul(2.0, x, c), hyp.mobius_add(x, x, c))
    # A rotation commutes with the ball: M (x)_c x = M x for orthogonal M.
    q, _ = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(9)))
    torch.testing.assert_close(hyp.mobius_matvec(q, x, c), x @ q.T)
    assert hyp.mobius_matvec(torch.zeros(2, 3, dtype=torch.float64), x, c).abs().max() == 0


def test_sq_dist_matrix_gradients():
    g = torch.Generator().manual_seed(10)
    x = (torch.randn(4, 3, generator=g, dtype=torch.float64) * 0.3).requires_grad_()
    p = (torch.randn(5, 3, generator=g, dtype=torch.float64) * 0.3).requires_grad_()
    c = torch.tensor(0.7, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(hyp.sq_dist_matrix, (x, p, c))


@pytest.mark.parametrize("scale", [1.0, 1e3, 1e8])
def test_layers_keep_points_inside_the_ball(scale):
    torch.manual_seed(0)
    cfg = HgcnTrainConfig(n_words=4, hidden_dim=8)
    n = 6
    rows = np.repeat(np.arange(n), n)
    cols = np.tile(np.arange(n), n)
    adj = sparse_tensor(rows, cols, np.full(n * n, 1.0 / n), (n, n))
    x = torch.randn(n, 5) * scale
    model = HGCN(5, 8, cfg)
    c = model.curvatures
    h0 = model.embed_input(x)
    layer = HGCNLayer(5, 8, 0.0, "relu")
    with torch.no_grad():
        layer.linear.weight.mul_(scale)
    for h, cv in ((h0, c[0]), (layer(h0, adj, c[0], c[1]), c[1]), (model.embed_all(x, adj), c[2])):
        assert torch.isfinite(h).all()
        assert (h.norm(dim=-1) < 1 / cv.sqrt()).all()
    protos = model.prototype_points(torch.randn(4, 5) * scale)
    h = model.embed_all(x, adj)
    logits = model.candidate_logits(h, protos, torch.arange(4).repeat(n, 1))
    assert torch.isfinite(logits).all()


@pytest.mark.parametrize("residual", [True, False])
@pytest.mark.parametrize("scale", [0.5, 30.0])
def test_tangent_space_evaluation_equals_ball_operations(scale, residual):
    # The training path (tangent vectors, closed-form log0(proj(exp0(.)))) must equal the
    # layer-by-layer ball operations of HGCN, including when the projection clips.
    torch.manual_seed(1)
    cfg = HgcnTrainConfig(n_words=5, hidden_dim=6, init_curvature=0.7, residual=residual)
    model = HGCN(4, 6, cfg).double()
    with torch.no_grad():
        model.raw_c.copy_(torch.tensor([0.3, -0.2, 0.8], dtype=torch.float64))
        for layer in model.layers:
            for lin in (layer.linear, layer.self_linear) if residual else (layer.linear,):
                lin.weight.normal_(0, 0.5)
                lin.bias.normal_()
    n = 7
    g = torch.Generator().manual_seed(2)
    dense = torch.rand(n, n, generator=g, dtype=torch.float64)
    dense = (dense + dense.T) / n
    rows, cols = np.nonzero(np.ones((n, n)))
    adj = sparse_tensor(rows, cols, dense.numpy()[rows, cols], (n, n)).double()
    x = torch.randn(n, 4, generator=g, dtype=torch.float64) * scale
    ref = model.forward_reference(x, adj, adj)
    got = model.forward_blocks(x, adj, adj)
    torch.testing.assert_close(got, ref, atol=1e-9, rtol=1e-7)
    v = torch.randn(n, 3, generator=g, dtype=torch.float64) * scale
    c = torch.tensor(1.3, dtype=torch.float64)
    torch.testing.assert_close(hyp.clip_tangent(v, c), hyp.logmap0(hyp.proj(hyp.expmap0(v, c), c), c))
