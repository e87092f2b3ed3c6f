"""The rounding bounds of models/rounding.py: they hold for every precision they are
derived for, and they are tight enough that a precision lower than claimed breaks them."""

import numpy as np
import pytest

from models import rounding as rd
from models.neural import NeuralSpec, make_export_module, make_torch_model, rounding_bound

def _model(seed, hidden=(64, 64, 64), relative=True, folds=("theta", "dphi"), lines=()):
    import torch

    spec = NeuralSpec(relative_phi=relative, hidden=list(hidden), s0=0.05, y_max=12.0, wavelength=[450.0, 550.0, 650.0],
                      table_hash="", config_hash="", reductions={}, folds=list(folds),
                      lines=list(lines), line_channels=6 if lines else 0)
    torch.manual_seed(seed)
    mlp = make_torch_model(spec)
    with torch.no_grad():  # outputs spread over the transform's range: small, large, clamped
        mlp[-1].bias.add_(1.5)
        if lines:  # nodes far from 1, of both signs: products that matter
            for line in mlp[0].lines:
                line.mul_(3).sub_(2)
    layers = [(m.weight.detach().numpy(), m.bias.detach().numpy()) for m in mlp if isinstance(m, torch.nn.Linear)]
    nodes = [line.detach().numpy() for line in mlp[0].lines] if lines else []
    return spec, make_export_module(spec, mlp).eval(), layers, nodes


def _queries(n=20_000, seed=0):
    rng = np.random.default_rng(seed)
    q = np.stack([rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2, np.pi / 2, n),
                  rng.uniform(-np.pi, np.pi, n), rng.uniform(-np.pi / 2, np.pi / 2, n)], -1)
    edges = [[0, np.pi / 2, np.pi, -np.pi / 2], [2 * np.pi, 0.3, 2 * np.pi + 1e-6, -0.3], [1e4, 3.0, -1e4, -3.0]]
    return np.concatenate([q, edges]).astype(np.float32)


@pytest.mark.parametrize("lines", [(), (8, 16, 12)])
@pytest.mark.parametrize("relative,folds", [(True, ("theta", "dphi")), (False, ("theta", "xz")), (True, ())])
def test_float32_and_float64_lie_within_their_bounds(relative, folds, lines):
    """Plain MLPs and MLPs with feature lines (periodic azimuth line: no folds)."""
    import torch

    spec, module, layers, nodes = _model(1, relative=relative, folds=folds, lines=lines)
    q = _queries()
    exact, b32 = rounding_bound(spec, layers, q, lines=nodes)
    _, b64 = rounding_bound(spec, layers, q, u=rd.U64, lines=nodes)
    with torch.no_grad():
        f32 = module(torch.from_numpy(q)).numpy().astype(np.float64)
        f64 = module.double()(torch.from_numpy(q).double()).numpy()
    assert np.all(np.abs(f64 - exact) <= b64)  # the bound's own float64 evaluation is the exact value's
    assert np.all(np.abs(f32 - f64) <= b32 + b64)
    # a bound, not a blanket: the float32 error uses a fair share of it somewhere
    assert np.max(np.abs(f32 - f64) / (b32 + b64)) > 1e-3


def test_a_lower_precision_breaks_the_float32_bound():
    """The same model evaluated in bfloat16 (u = 2^-8) lies far outside the float32 bound:
    the float32 check tells a lower precision somewhere in a backend apart."""
    import torch

    spec, module, layers, _ = _model(2)
    q = _queries(5000)
    exact, b32 = rounding_bound(spec, layers, q)
    with torch.no_grad():
        bf16 = module.to(torch.bfloat16)(torch.from_numpy(q).to(torch.bfloat16)).float().numpy().astype(np.float64)
    assert np.max(np.abs(bf16 - exact) / b32) > 10


def test_bounded_arithmetic_covers_each_operation():
    x = rd.Bounded.exact(np.float32(0.1))
    y = (x * 3.0 + 1.0 / 3.0) - x
    exact = float(np.float32(0.1)) * 2.0 + 1.0 / 3.0  # of the float32 input 0.1f
    computed = (np.float32(0.1) * np.float32(3.0) + np.float32(1.0 / 3.0)) - np.float32(0.1)
    assert abs(float(computed) - exact) <= float(y.err)
    assert abs(y.value - exact) < 1e-15
    # sin of a rounded argument: the derivative carries the operand's error
    t = rd.Bounded.exact(np.float32(1e4)) - rd.Bounded.exact(np.float32(-1e4))
    s = rd.sin(t)
    assert abs(float(np.sin(np.float32(1e4) - np.float32(-1e4))) - np.sin(2e4)) <= float(s.err)
    # a comparison within the error of its operands is flagged, and where() takes both branches
    m = rd.Bounded(0.01, 1e-9) < 0.01
    assert m.ambiguous and rd.where(m, rd.Bounded(1.0), rd.Bounded(2.0)).err >= 1.0
    assert rd.gamma(10) == pytest.approx(10 * 2.0 ** -24, rel=1e-6)
