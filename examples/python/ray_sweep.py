"""A sweep of the cavity pressure of the cuboid actuator as Ray tasks: the tip's steady
displacement from 0 to 300 kPa (the pressure study's optimum is ~275 kPa), written to a CSV and a plot.

    python examples/python/ray_sweep.py [--points N] [--out DIR] [--address ADDRESS]

Each task is one static solve of `examples/pressure_optimization.soft` (with --address, on a
running Ray cluster; the script and its mesh must be at the same path on every node).
"""

import argparse
import csv
import os
import pathlib

import ray

import softc.ray

HERE = pathlib.Path(__file__).resolve().parent


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=int, default=16)
    ap.add_argument("--out", default="sweep")
    ap.add_argument("--address", default=None, help="a Ray cluster's address (default: local)")
    args = ap.parse_args()

    ray.init(address=args.address, include_dashboard=False, log_to_driver=False)
    pressures = [300e3 * i / (args.points - 1) for i in range(args.points)]
    results = softc.ray.map(HERE.parent / "pressure_optimization.soft",
                            [{"p_max": p} for p in pressures])
    ray.shutdown()

    os.makedirs(args.out, exist_ok=True)
    rows = []
    for p, r in zip(pressures, results):
        u = r["sets"]["tip"]["mean_displacement"]
        rows.append((p, u[0], u[1], u[2], r["solver"]["newton_iterations"]))
    path = os.path.join(args.out, "sweep.csv")
    with open(path + ".tmp", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["p_max_Pa", "tip_ux_m", "tip_uy_m", "tip_uz_m", "newton_iterations"])
        w.writerows(rows)
    os.replace(path + ".tmp", path)
    print(f"wrote {path}")
    for p, _, _, uz, n in rows:
        print(f"p_max = {p / 1e3:5.1f} kPa: tip z {uz * 1e3:8.3f} mm ({n} Newton iterations)")

    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib is not installed: no plot (pip install matplotlib)")
        return
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot([r[0] / 1e3 for r in rows], [r[3] * 1e3 for r in rows], "o-")
    ax.set_xlabel("cavity pressure (kPa)")
    ax.set_ylabel("tip vertical displacement (mm)")
    ax.set_title("cuboid actuator, static solves")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    png = os.path.join(args.out, "sweep.png")
    fig.savefig(png + ".tmp.png", dpi=120)
    os.replace(png + ".tmp.png", png)
    print(f"wrote {png}")


if __name__ == "__main__":
    main()
