"""The Python examples run (short versions), and the PyTorch controller is the script's."""

import subprocess
import sys

import numpy as np
import pytest

torch = pytest.importorskip("torch")
import softc  # noqa: E402
import softc.torch  # noqa: E402
from conftest import EXAMPLES  # noqa: E402

PY = EXAMPLES / "python"


def run_example(name, *args, cwd=None):
    result = subprocess.run(
        [sys.executable, str(PY / name), *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    return result.stdout


def test_pressure_adam_example():
    out = run_example("pressure_adam.py", "--iterations", "3")
    assert "iteration  2" in out and "tip's mean vertical displacement" in out


def test_controller_example():
    out = run_example("controller_torch.py", "--iterations", "2")
    assert out.count("held-out target") == 4


def test_ray_sweep_example(tmp_path):
    pytest.importorskip("ray")
    out = run_example("ray_sweep.py", "--points", "3", "--out", str(tmp_path))
    lines = (tmp_path / "sweep.csv").read_text().splitlines()
    assert lines[0].startswith("p_max_Pa") and len(lines) == 4
    # More pressure bends the tip further down.
    z = [float(line.split(",")[3]) for line in lines[1:]]
    assert z[0] == 0.0 and z[2] < z[1] < 0.0
    assert "wrote" in out


def test_the_torch_controller_is_the_scripts_controller(endoscope):
    """controller_torch.py's network through SceneLoss gives the loss and d loss / d w of the
    in-script controller of controller_synthesis.soft, at the same weights and targets."""
    sys.path.insert(0, str(PY))
    try:
        import controller_torch
    finally:
        sys.path.pop(0)
    script = softc.compile(EXAMPLES / "controller_synthesis.soft")
    w = np.array([[400.0, -300.0, 250.0, 100.0],
                  [-200.0, 350.0, 50.0, -150.0],
                  [100.0, 80.0, -400.0, 300.0]])  # 1/mm
    targets = torch.tensor([[0, 20e-6, 30e-6], [0, -30e-6, 10e-6]], dtype=torch.float64)
    net = controller_torch.Controller()
    with torch.no_grad():
        net.layer.weight.copy_(torch.as_tensor(w))
    loss_fn = softc.torch.SceneLoss(endoscope)
    losses = loss_fn(p=net(targets), inputs={"target": targets})
    losses.mean().backward()
    expected_losses = []
    expected_grad = np.zeros((3, 4))
    for t in targets:
        loss, g = script.loss_and_grad({"w": w * 1e3}, inputs={"target": t.numpy()})
        expected_losses.append(loss)
        # The script's w is in 1/m: d/d(w in 1/mm) = 1e3 d/d(w in 1/m).
        expected_grad += 1e3 * g["w"] / len(targets)
    np.testing.assert_allclose(losses.detach().numpy(), expected_losses, rtol=1e-9)
    np.testing.assert_allclose(net.layer.weight.grad.numpy(), expected_grad, rtol=1e-7,
                               atol=1e-9 * np.abs(expected_grad).max())


def test_gripper_example():
    out = run_example("gripper_torch.py", "--iterations", "3")
    assert "iteration  2" in out and "grip left" in out
