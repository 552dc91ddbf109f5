"""The controller study (thesis §6) with the controller in PyTorch: a 4→3 torch.nn.Linear with
the scaled sigmoid of eq. 6.2 maps a target point of the endoscope's free end to its three
chamber pressures, and softc's static solve of `controller_scene.soft` (the study's scene with
the controller taken out) is the differentiable loss of each target, through SceneLoss.

    python examples/python/controller_torch.py [--iterations N] [--seed S]

The network is the in-script controller of `examples/controller_synthesis.soft`: for the same
weights and targets, the batch loss and its gradient with respect to the weights are the ones
`softc run examples/controller_synthesis.soft --grad` computes (the test suite checks it to
1e-9). The training loop is PyTorch's own (Adam on fresh targets every iteration), so its path
differs from the script's SGD with eq. 5.5.
"""

import argparse
import math
import pathlib

import torch

import softc
import softc.torch

HERE = pathlib.Path(__file__).resolve().parent
RADIUS = 40e-6  # m: the targets' circle, as in controller_synthesis.soft


def features(target):
    """Thesis eq. 6.1: each target component (y, z) split at zero; in mm."""
    y, z = target[..., 1] * 1e3, target[..., 2] * 1e3
    zero = torch.zeros_like(y)
    return torch.stack([torch.maximum(zero, y), torch.minimum(zero, y),
                        torch.maximum(zero, z), torch.minimum(zero, z)], dim=-1)


class Controller(torch.nn.Module):
    """20 kPa · sigmoid(w · features(target)); w in 1/mm, initialised at zero (the thesis')."""

    def __init__(self):
        super().__init__()
        self.layer = torch.nn.Linear(4, 3, bias=False, dtype=torch.float64)
        torch.nn.init.zeros_(self.layer.weight)

    def forward(self, target):
        return 20e3 * torch.sigmoid(self.layer(features(target)))


def quadrant_targets(generator, batch=4):
    """One target per quadrant of the circle in the y-z plane, uniform over its area."""
    r = RADIUS * torch.sqrt(torch.rand(batch, generator=generator, dtype=torch.float64))
    angle = (torch.arange(batch) % 4 + torch.rand(batch, generator=generator,
                                                  dtype=torch.float64)) * math.pi / 2
    return torch.stack([torch.zeros(batch, dtype=torch.float64), r * torch.cos(angle),
                        r * torch.sin(angle)], dim=-1)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=30)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--lr", type=float, default=5.0)
    args = ap.parse_args()

    scene = softc.compile(HERE / "controller_scene.soft")
    loss_fn = softc.torch.SceneLoss(scene)
    controller = Controller()
    # Adam's steps are ~lr in the weights' units (1/mm); the script's bounds are ±1250 /mm.
    opt = torch.optim.Adam(controller.parameters(), lr=args.lr)
    generator = torch.Generator().manual_seed(args.seed)
    for it in range(args.iterations):
        targets = quadrant_targets(generator)
        opt.zero_grad()
        losses = loss_fn(p=controller(targets), inputs={"target": targets})
        # In um^2: Adam's epsilon (1e-8) would swamp gradients of a loss in m^2 (~1e-11).
        loss = losses.mean() * 1e12
        loss.backward()
        opt.step()
        print(f"iteration {it:2d}: batch loss {loss.item():10.3f} um^2")

    # Held out: the script's four validation targets.
    held_out = torch.tensor([[0, 20, 34.64], [0, -34.64, 20], [0, -20, -34.64],
                             [0, 34.64, -20]], dtype=torch.float64) * 1e-6
    with torch.no_grad():
        errors = loss_fn(p=controller(held_out), inputs={"target": held_out}).sqrt()
    for t, e in zip(held_out, errors):
        print(f"held-out target ({t[1] * 1e6:6.2f}, {t[2] * 1e6:6.2f}) um: miss {e.item() * 1e6:.2f} um")
    print("weights (1/mm):")
    print(controller.layer.weight.detach())


if __name__ == "__main__":
    main()
