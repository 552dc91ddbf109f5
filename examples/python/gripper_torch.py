"""The gripper study (issue 32) as a PyTorch loop: the chamber pressure and the silicone's shear
modulus at which each finger of the soft gripper squeezes the cylinder with 40 mN while its
outer wall stays below a stretch of 1.3, by torch.optim.Adam on softc's static solve with
contact and its exact gradient.

    python examples/python/gripper_torch.py [--iterations N]

`examples/gripper.soft` is the same study as a script. Its loss (the grip miss plus the stretch
penalty) is computed by softc; torch holds the two design variables, mapped into the script's
bounds as the script's optimizer maps them (SPEC 5.6: lo + (hi - lo) * sigmoid(u)), and each
static solve starts from the last one's equilibrium (`warm_start=True`).
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

    scene = softc.compile(HERE.parent / "gripper.soft", warm_start=True)
    loss_fn = softc.torch.SceneLoss(scene)
    bounds = {name: (scene.params[name].lower, scene.params[name].upper) for name in ("p", "mu")}

    def unconstrained(name):
        lo, hi = bounds[name]
        s = (scene.params[name].initial - lo) / (hi - lo)
        return torch.tensor(math.log(s / (1 - s)), dtype=torch.float64, requires_grad=True)

    def design(u):
        return {name: lo + (hi - lo) * torch.sigmoid(u[name]) for name, (lo, hi) in bounds.items()}

    u = {name: unconstrained(name) for name in bounds}
    opt = torch.optim.Adam(list(u.values()), lr=0.15, betas=(0.5, 0.999))
    for it in range(args.iterations):
        opt.zero_grad()
        values = design(u)
        loss = loss_fn(**values)
        loss.backward()
        print(f"iteration {it:2d}: p = {values['p'].item() / 1e3:7.3f} kPa, "
              f"mu = {values['mu'].item() / 1e3:7.3f} kPa, loss = {loss.item():9.4f}")
        if loss.item() < 1.0:  # the script's `stop when loss < 1`
            break
        opt.step()
    final = {name: v.item() for name, v in design(u).items()}
    summary = scene.run(final)
    grips = ", ".join(f"{c['body']} {abs(c['force'][0]) * 1e3:.1f} mN" for c in summary["contact"])
    print(f"p = {final['p'] / 1e3:.3f} kPa, mu = {final['mu'] / 1e3:.3f} kPa: grip {grips}")


if __name__ == "__main__":
    main()
