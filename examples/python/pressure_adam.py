"""The pressure study (thesis §5.3) as a PyTorch loop: find the chamber pressure that moves the
cuboid's free end 10 mm down, with torch.optim.Adam on softc's static solve and its exact
gradient (the implicit function theorem, one transposed solve per iteration).

    python examples/python/pressure_adam.py [--iterations N]

`examples/pressure_optimization.soft` is the same study as a script (NAdam with eq. 5.5).
"""

import argparse
import math
import pathlib

import torch

import softc
import softc.torch

HERE = pathlib.Path(__file__).resolve().parent


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--iterations", type=int, default=40)
    args = ap.parse_args()

    scene = softc.compile(HERE.parent / "pressure_optimization.soft")
    loss_fn = softc.torch.SceneLoss(scene)
    # Optimize u = ln(p_max / 1 kPa): relative steps, the natural scale of a pressure (the
    # script's lower-bounded p_max is optimized the same way, SPEC 5.6). softc takes SI.
    u = torch.tensor(math.log(scene.params["p_max"].initial / 1e3), dtype=torch.float64,
                     requires_grad=True)
    # A short memory of past gradients (beta1 = 0.5): the default 0.9 overshoots the optimum and
    # oscillates around it for tens of iterations.
    opt = torch.optim.Adam([u], lr=0.3, betas=(0.5, 0.999))
    for it in range(args.iterations):
        opt.zero_grad()
        p_max = 1e3 * torch.exp(u)
        loss = loss_fn(p_max=p_max)
        loss.backward()
        print(f"iteration {it:2d}: p_max = {p_max.item() / 1e3:8.3f} kPa, "
              f"loss = {loss.item() * 1e6:10.4f} mm^2")
        if loss.item() < 3.2e-6:  # the script's `stop when loss < 3.2 mm^2`
            break
        opt.step()
    p_kpa = torch.exp(u).detach()
    summary = scene.run({"p_max": p_kpa.item() * 1e3})
    tip_z = summary["sets"]["tip"]["mean_displacement"][2]
    print(f"p_max = {p_kpa.item():.3f} kPa: the tip's mean vertical displacement is "
          f"{tip_z * 1e3:.3f} mm (target -10 mm)")


if __name__ == "__main__":
    main()
