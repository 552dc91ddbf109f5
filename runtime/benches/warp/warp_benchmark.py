"""The canonical benchmark scene (shared/BENCHMARK.md) in NVIDIA Warp, for a side-by-side
timing with `softc bench`.

Same mesh (the gmsh 4.1 files under meshes/, read here), same physics as
examples/benchmark-*.soft: coupled (ln J) compressible neo-Hookean, E = 0.3 MPa, nu = 0.45,
lumped masses rho*V0/4, follower pressure p*A*n/3 per chamber triangle with
p(t) = p_peak * min(t / 0.5 s, 1), semi-implicit Euler with mass-proportional damping
beta = 20 /s, nodes at x = 0 fixed; f32 on Warp's CPU device.

Timed, like `softc bench`: forward steps/s (median of --repeats runs of --steps steps after a
warm-up run) and forward+backward steps/s over --grad-steps steps: every step recorded on a
wp.Tape, the loss sum over tip nodes (z - z0 + 10 mm)^2 at the end, tape.backward() to
d loss / d p_peak. Warp keeps every step's state for the tape (no checkpointing).

Written for softc's benchmark; not derived from Warp's examples.
"""

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

ROOT = Path(__file__).resolve().parents[3]
DT = {"1k": 40e-6, "10k": 20e-6, "50k": 12.5e-6}

E, NU, RHO, BETA, P_PEAK, RAMP = 0.3e6, 0.45, 1070.0, 20.0, 3e3, 0.5
MU = E / (2 * (1 + NU))
LAM = E * NU / ((1 + NU) * (1 - 2 * NU))


def read_msh(path):
    """Nodes (mm), tets (0-based), and the triangles of each tagged physical surface."""
    lines = Path(path).read_text().split("\n")
    i = 0
    names, surf_phys = {}, {}
    nodes, tets, tris = {}, [], {}
    while i < len(lines):
        line = lines[i].strip()
        if line == "$PhysicalNames":
            n = int(lines[i + 1])
            for k in range(n):
                dim, tag, name = lines[i + 2 + k].split(maxsplit=2)
                names[(int(dim), int(tag))] = name.strip('"')
            i += n + 2
        elif line == "$Entities":
            npt, ncu, nsu, nvo = map(int, lines[i + 1].split())
            j = i + 2 + npt + ncu
            for k in range(nsu):
                f = lines[j + k].split()
                nphys = int(f[7])
                surf_phys[int(f[0])] = [int(t) for t in f[8 : 8 + nphys]]
            i = j + nsu + nvo
        elif line == "$Nodes":
            nblocks = int(lines[i + 1].split()[0])
            j = i + 2
            for _ in range(nblocks):
                _, _, _, n = map(int, lines[j].split())
                tags = [int(lines[j + 1 + k]) for k in range(n)]
                for k in range(n):
                    nodes[tags[k]] = [float(c) for c in lines[j + 1 + n + k].split()]
                j += 1 + 2 * n
            i = j
        elif line == "$Elements":
            nblocks = int(lines[i + 1].split()[0])
            j = i + 2
            for _ in range(nblocks):
                dim, ent, etype, n = map(int, lines[j].split())
                rows = [list(map(int, lines[j + 1 + k].split()[1:])) for k in range(n)]
                if etype == 4:
                    tets += rows
                elif etype == 2:
                    for p in surf_phys.get(ent, []):
                        tris.setdefault(names[(2, p)], []).extend(rows)
                j += 1 + n
            i = j
        else:
            i += 1
    order = sorted(nodes)
    index = {t: k for k, t in enumerate(order)}
    x = np.array([nodes[t] for t in order], dtype=np.float64)
    tets = np.array([[index[t] for t in r] for r in tets], dtype=np.int32)
    tris = {k: np.array([[index[t] for t in r] for r in v], dtype=np.int32) for k, v in tris.items()}
    return x, tets, tris


@wp.kernel
def element_forces(
    x: wp.array(dtype=wp.vec3),
    tets: wp.array(dtype=wp.int32, ndim=2),
    dm_inv: wp.array(dtype=wp.mat33),
    vol0: wp.array(dtype=float),
    mu: float,
    lam: float,
    f: wp.array(dtype=wp.vec3),
):
    e = wp.tid()
    i0, i1, i2, i3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    x0 = x[i0]
    ds = wp.matrix_from_cols(x[i1] - x0, x[i2] - x0, x[i3] - x0)
    F = ds * dm_inv[e]
    J = wp.determinant(F)
    finv_t = wp.transpose(wp.inverse(F))
    # Psi = mu/2 (tr FtF - 3) - mu ln J + lam/2 (ln J)^2  =>  P = mu (F - F^-T) + lam ln J F^-T
    P = mu * (F - finv_t) + lam * wp.log(J) * finv_t
    H = -vol0[e] * (P * wp.transpose(dm_inv[e]))
    h1, h2, h3 = wp.vec3(H[0, 0], H[1, 0], H[2, 0]), wp.vec3(H[0, 1], H[1, 1], H[2, 1]), wp.vec3(H[0, 2], H[1, 2], H[2, 2])
    wp.atomic_add(f, i0, -(h1 + h2 + h3))
    wp.atomic_add(f, i1, h1)
    wp.atomic_add(f, i2, h2)
    wp.atomic_add(f, i3, h3)


@wp.kernel
def pressure_forces(
    x: wp.array(dtype=wp.vec3),
    tris: wp.array(dtype=wp.int32, ndim=2),
    p_peak: wp.array(dtype=float),
    t: float,
    f: wp.array(dtype=wp.vec3),
):
    k = wp.tid()
    a, b, c = tris[k, 0], tris[k, 1], tris[k, 2]
    p = p_peak[0] * wp.min(t / 0.5, 1.0)
    # p * A * n / 3 = p/6 (x1 - x0) x (x2 - x0); triangles are wound into the solid.
    g = (p / 6.0) * wp.cross(x[b] - x[a], x[c] - x[a])
    wp.atomic_add(f, a, g)
    wp.atomic_add(f, b, g)
    wp.atomic_add(f, c, g)


@wp.kernel
def integrate(
    x: wp.array(dtype=wp.vec3),
    v: wp.array(dtype=wp.vec3),
    f: wp.array(dtype=wp.vec3),
    inv_mass: wp.array(dtype=float),
    free: wp.array(dtype=float),
    dt: float,
    beta: float,
    x_out: wp.array(dtype=wp.vec3),
    v_out: wp.array(dtype=wp.vec3),
):
    n = wp.tid()
    v1 = (v[n] + dt * (f[n] * inv_mass[n] - beta * v[n])) * free[n]
    v_out[n] = v1
    x_out[n] = x[n] + dt * v1


@wp.kernel
def tip_loss(
    x: wp.array(dtype=wp.vec3),
    x0: wp.array(dtype=wp.vec3),
    tip: wp.array(dtype=wp.int32),
    loss: wp.array(dtype=float),
):
    k = wp.tid()
    n = tip[k]
    d = x[n][2] - x0[n][2] + 0.01
    wp.atomic_add(loss, 0, d * d)


class Scene:
    def __init__(self, size, device="cpu"):
        x_mm, tets, tris = read_msh(ROOT / "meshes" / f"bench_{size}.msh")
        x = x_mm * 1e-3
        self.size, self.dt, self.device = size, DT[size], device
        self.n_nodes, self.n_tets = len(x), len(tets)
        ds = np.stack([x[tets[:, k]] - x[tets[:, 0]] for k in (1, 2, 3)], axis=2)
        vol = np.linalg.det(ds) / 6.0
        assert (vol > 0).all(), "tets are positively oriented"
        mass = np.zeros(len(x))
        for k in range(4):
            np.add.at(mass, tets[:, k], RHO * vol / 4.0)
        fixed = np.abs(x[:, 0]) < 1e-12
        tip = np.nonzero(np.abs(x[:, 0] - 0.06) < 1e-12)[0].astype(np.int32)
        kw = dict(device=device)
        self.x0 = wp.array(x.astype(np.float32), dtype=wp.vec3, **kw)
        self.tets = wp.array(tets, dtype=wp.int32, **kw)
        self.tris = wp.array(tris["cavity"], dtype=wp.int32, **kw)
        self.dm_inv = wp.array(np.linalg.inv(ds).astype(np.float32), dtype=wp.mat33, **kw)
        self.vol0 = wp.array(vol.astype(np.float32), dtype=float, **kw)
        self.inv_mass = wp.array((1.0 / mass).astype(np.float32), dtype=float, **kw)
        self.free = wp.array((~fixed).astype(np.float32), dtype=float, **kw)
        self.tip = wp.array(tip, dtype=wp.int32, **kw)
        self.p_peak = wp.array([P_PEAK], dtype=float, requires_grad=True, **kw)

    def step(self, k, x, v, f, x_out, v_out):
        t = k * self.dt
        f.zero_()
        wp.launch(element_forces, self.n_tets, inputs=[x, self.tets, self.dm_inv, self.vol0, MU, LAM, f], device=self.device)
        wp.launch(pressure_forces, len(self.tris), inputs=[x, self.tris, self.p_peak, t, f], device=self.device)
        wp.launch(integrate, self.n_nodes, inputs=[x, v, f, self.inv_mass, self.free, self.dt, BETA, x_out, v_out], device=self.device)

    def forward(self, steps):
        """`steps` steps ping-ponging two states; returns the tip's mean z-displacement (m)."""
        x = [wp.clone(self.x0), wp.zeros_like(self.x0)]
        v = [wp.zeros_like(self.x0), wp.zeros_like(self.x0)]
        f = wp.zeros_like(self.x0)
        for k in range(steps):
            self.step(k, x[k % 2], v[k % 2], f, x[(k + 1) % 2], v[(k + 1) % 2])
        wp.synchronize_device(self.device)
        return self.tip_mean_z(x[steps % 2])

    def tip_mean_z(self, x):
        tip = self.tip.numpy()
        return float((x.numpy()[tip, 2] - self.x0.numpy()[tip, 2]).mean())

    def alloc_tape_states(self, steps):
        z = lambda: wp.zeros(self.n_nodes, dtype=wp.vec3, device=self.device, requires_grad=True)
        xs = [wp.clone(self.x0, requires_grad=True)] + [z() for _ in range(steps)]
        vs = [z() for _ in range(steps + 1)]
        fs = [z() for _ in range(steps)]
        return xs, vs, fs

    def forward_backward(self, steps, states):
        """Every step on a tape, the loss at the end, its gradient w.r.t. p_peak."""
        xs, vs, fs = states
        for a in xs[1:] + vs + fs:
            a.zero_()
        self.p_peak.grad.zero_()
        loss = wp.zeros(1, dtype=float, device=self.device, requires_grad=True)
        tape = wp.Tape()
        with tape:
            for k in range(steps):
                self.step(k, xs[k], vs[k], fs[k], xs[k + 1], vs[k + 1])
            wp.launch(tip_loss, len(self.tip), inputs=[xs[steps], self.x0, self.tip, loss], device=self.device)
        tape.backward(loss=loss)
        wp.synchronize_device(self.device)
        g = float(self.p_peak.grad.numpy()[0])
        tape.reset()
        return float(loss.numpy()[0]), g


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", default="1k,10k,50k")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--grad-steps", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--only", choices=["forward", "backward"], help="time only one of the two (for instruction counts)")
    ap.add_argument("--json", help="also write the rows here")
    a = ap.parse_args()
    wp.config.quiet = True
    wp.init()
    rows = []
    for size in a.sizes.split(","):
        s = Scene(size)
        row = {"size": size, "tets": s.n_tets, "dt": s.dt, "steps": a.steps, "grad_steps": a.grad_steps}
        if a.only != "backward":
            s.forward(a.steps)  # warm-up (kernel compilation and load)
            speeds = []
            for _ in range(a.repeats):
                t0 = time.perf_counter()
                z = s.forward(a.steps)
                speeds.append(a.steps / (time.perf_counter() - t0))
            row.update(forward_steps_per_second=statistics.median(speeds), tip_mean_z=z)
        if a.only != "forward":
            states = s.alloc_tape_states(a.grad_steps)
            s.forward_backward(a.grad_steps, states)  # warm-up
            speeds = []
            for _ in range(a.repeats):
                t0 = time.perf_counter()
                loss, g = s.forward_backward(a.grad_steps, states)
                speeds.append(a.grad_steps / (time.perf_counter() - t0))
            row.update(forward_backward_steps_per_second=statistics.median(speeds), loss=loss, gradient_p_peak=g)
        rows.append(row)
        print(json.dumps(row), flush=True)
    if a.json:
        Path(a.json).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    sys.exit(main())
