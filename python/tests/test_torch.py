"""softc.torch.SceneLoss: the loss as a tensor, and backward through softc's adjoint."""

import numpy as np
import pytest

torch = pytest.importorskip("torch")
import softc  # noqa: E402
import softc.torch  # noqa: E402


def test_backward_gives_loss_and_grad(beam):
    loss_fn = softc.torch.SceneLoss(beam)
    p0 = torch.tensor(12e3, dtype=torch.float64, requires_grad=True)
    mu = torch.tensor(beam.params["mu"].initial, dtype=torch.float64, requires_grad=True)
    loss = loss_fn(p0=p0, mu=mu)
    assert loss.shape == () and loss.dtype == torch.float64
    loss.backward()
    expected_loss, expected = beam.loss_and_grad({"p0": 12e3, "mu": beam.params["mu"].initial})
    assert loss.item() == expected_loss
    assert p0.grad.item() == expected["p0"]
    np.testing.assert_array_equal(mu.grad.numpy(), expected["mu"])


def test_chain_rule_through_a_torch_expression(beam):
    """The loss of p0 = 3 * a: d/da = 3 * d/dp0, and an upstream factor scales it."""
    loss_fn = softc.torch.SceneLoss(beam, steps=120)
    a = torch.tensor(4e3, dtype=torch.float64, requires_grad=True)
    (2.0 * loss_fn(p0=3 * a)).backward()
    _, g = beam.loss_and_grad({"p0": 12e3}, steps=120)
    assert a.grad.item() == pytest.approx(2.0 * 3.0 * g["p0"], rel=1e-15)


def test_float32_tensors(beam):
    loss_fn = softc.torch.SceneLoss(beam, steps=100)
    p0 = torch.tensor(12e3, dtype=torch.float32, requires_grad=True)
    loss = loss_fn(p0=p0)
    assert loss.dtype == torch.float32
    loss.backward()
    assert p0.grad.dtype == torch.float32
    _, g = beam.loss_and_grad({"p0": 12e3}, steps=100)
    assert p0.grad.item() == pytest.approx(g["p0"], rel=1e-6)


def test_no_grad_runs_forward_only(beam):
    loss_fn = softc.torch.SceneLoss(beam, steps=50)
    with torch.no_grad():
        loss = loss_fn(p0=torch.tensor(9e3, dtype=torch.float64))
    assert loss.item() == beam.run({"p0": 9e3}, steps=50)["loss"]


def test_a_batch_of_targets_and_pressures(endoscope):
    """A batch dimension on the inputs and on a param: one scene per row, per-row losses, and
    the gradient of their sum is each row's own gradient."""
    loss_fn = softc.torch.SceneLoss(endoscope)
    targets = torch.tensor([[0, 20e-6, 30e-6], [0, -30e-6, 10e-6]], dtype=torch.float64)
    p = torch.tensor([[12e3, 6e3, 3e3], [2e3, 14e3, 5e3]], dtype=torch.float64, requires_grad=True)
    losses = loss_fn(p=p, inputs={"target": targets})
    assert losses.shape == (2,)
    losses.sum().backward()
    for b in range(2):
        loss, g = endoscope.loss_and_grad({"p": p[b].detach().numpy()},
                                          inputs={"target": targets[b].numpy()})
        assert losses[b].item() == loss
        np.testing.assert_array_equal(p.grad[b].numpy(), g["p"])


def test_a_shared_param_sums_over_the_batch(endoscope):
    loss_fn = softc.torch.SceneLoss(endoscope)
    targets = torch.tensor([[0, 20e-6, 30e-6], [0, -30e-6, 10e-6]], dtype=torch.float64)
    p = torch.tensor([12e3, 6e3, 3e3], dtype=torch.float64, requires_grad=True)
    loss_fn(p=p, inputs={"target": targets}).mean().backward()
    grads = [endoscope.loss_and_grad({"p": [12e3, 6e3, 3e3]}, inputs={"target": t.numpy()})[1]["p"]
             for t in targets]
    np.testing.assert_allclose(p.grad.numpy(), (grads[0] + grads[1]) / 2, rtol=1e-15)


def test_wrong_names_and_shapes(beam):
    loss_fn = softc.torch.SceneLoss(beam)
    with pytest.raises(softc.ParamError):
        loss_fn(q=torch.tensor(1.0))
    with pytest.raises(ValueError, match="shape"):
        loss_fn(p0=torch.zeros(2, 3))
    with pytest.raises(TypeError):
        softc.torch.SceneLoss(beam, stpes=10)


def test_adam_lowers_the_loss(static_pressure):
    """Three Adam steps on the static pressure study move toward the 10 mm target."""
    loss_fn = softc.torch.SceneLoss(static_pressure)
    kpa = torch.tensor(10.0, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([kpa], lr=2.0)
    losses = []
    for _ in range(3):
        opt.zero_grad()
        loss = loss_fn(p_max=kpa * 1e3)
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < losses[0]
