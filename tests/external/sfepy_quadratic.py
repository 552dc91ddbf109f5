"""Same-mesh check of softc's static verification problem against SfePy (issue 30).

Run by hand, not in CI: SfePy is not a CI dependency. It needs SfePy (tested with 2026.3),
meshio and numpy, e.g. the venv ~/.cache/softc/py-venv, and a release build of softc:

    cargo build --release -p softc
    ~/.cache/softc/py-venv/bin/python tests/external/sfepy_quadratic.py \
        [--softc target/release/softc] [--mesh meshes/bench_1k.msh ...] [--order 1 2]

The problem is `examples/verification_quadratic.soft` (and, with order 1,
`examples/verification_static.soft`): the cuboid family of meshes (gmsh 4.1, mm), Yeoh
W = c10(I1b-3) + c20(I1b-3)^2 + c30(I1b-3)^3 + (J-1)^2/d1 with c10 = 0.24162 MPa,
c20 = 0.19977 MPa, c30 = -0.00541 MPa, d1 = 1/MPa; every node with x <= 0.5 mm clamped; a
follower pressure of 20 kPa and 30 kPa on the physical surface "cavity", pushing into the
solid; static equilibrium. Output: the mean z-displacement of the nodes with x > 59.9 mm (for
order 2 that includes the mid-edge nodes of the tip face, as softc's `select` does).

softc: the example with the mesh path replaced, `precision = f64` added to the sim block, and
`order: 1` or `order: 2` in `load`, run by `softc run`; the tip mean is read from its JSON.

SfePy, written independently of softc's code: total Lagrangian hyperelasticity on the same
linear geometry, a vector field of approx_order 1 or 2 (SfePy's P2 on straight-sided tets is
softc's `order: 2` discretization), terms
  dw_tl_he_genyeoh  (K1, K2, K3, m, p, q) = (c10, c20, c30, 1, 2, 3):
                    W = sum K (I1b - 3)^m, its stress S = 2 J^(-2/3) W'(I1b) (I - I1/3 C^-1)
  dw_tl_bulk_penalty K = 2/d1: S = K (J-1) J C^-1, i.e. W = K/2 (J-1)^2 = (J-1)^2/d1
  dw_tl_surface_traction with sigma = p I on the cavity facets: integral of p J F^-T N . v dA =
                    integral of p n . v da (n the outward normal of the solid), added to the
                    internal forces, so the load is -p n: the chamber inflates.
Volume quadrature: SfePy's order-2 tetrahedron rule, the 4-point rule softc uses for P2 (for
P1 the integrand is constant). Surface quadrature: order 6 on triangles (12 points), exact for
the pressure on flat 6-node faces (degree 4). Cavity facets: exactly the triangles of the gmsh
physical surface "cavity" (checked triangle by triangle). Newton (nls.newton, scipy direct
solver) from the undeformed state through a few load increments, to a residual of ~1e-12 of
the load's.

Measured (2 shared CPU cores, softc at 0bc31ae, SfePy 2026.3 with SciPy's SuperLU;
`--mesh meshes/bench_1k.msh` in 28 s, `--mesh meshes/cuboid.msh` in 12 min):

    mesh             order  p [kPa]        softc tip z [m]        SfePy tip z [m]  rel. diff
    bench_1k.msh         1       20 -1.251224641937148e-04 -1.251224648482620e-04   5.23e-09
    bench_1k.msh         1       30 -1.945551878090245e-04 -1.945551878073815e-04   8.44e-12
    bench_1k.msh         2       20 -1.455762122544530e-04 -1.455762122545300e-04   5.29e-13
    bench_1k.msh         2       30 -2.383524670798172e-04 -2.383524670798167e-04   2.16e-15
    cuboid.msh           1       20 -2.238667044706401e-04 -2.238667048326234e-04   1.62e-09
    cuboid.msh           1       30 -3.593622612993295e-04 -3.593622612991491e-04   5.02e-13
    cuboid.msh           2       20 -2.328593127246985e-04 -2.328593127245039e-04   8.35e-13
    cuboid.msh           2       30 -3.830686066594775e-04 -3.830686066627919e-04   8.65e-12

Tip nodes: 25 / 81 (bench_1k, P1 / P2) and 99 / 357 (cuboid), the same in both codes. Dofs
(clamped included): bench_1k 975 / 5,904, cuboid 6,912 / 46,746. Wall times: bench_1k P2
softc 6.7 s, SfePy 17.8 s; cuboid P1 softc 2.0 s, SfePy 17.7 s; cuboid P2 softc 66.5 s, SfePy
628 s (both pressures, on cores shared with other builds). The linear 20 kPa rows differ by
~1e-9: softc's Newton stops there at its own residual tolerance (SfePy's residual is 1e-13 of
the load); every quadratic row agrees to < 1e-11.
"""

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time

import numpy as nm

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

C10, C20, C30 = 0.24162e6, 0.19977e6, -0.00541e6  # Pa
D1 = 1.0e-6  # 1/Pa
PRESSURES = [20e3, 30e3]  # Pa
CLAMP_X = 0.5e-3  # m
TIP_X = 59.9e-3  # m


# ---------------------------------------------------------------------------------------------
# softc


def run_softc(softc, mesh_path, order):
    """Runs softc's quadratic verification example on `mesh_path` at `order`; returns
    {pressure: tip mean z} and the wall time."""
    with open(os.path.join(REPO, "examples", "verification_quadratic.soft")) as f:
        src = f.read()
    src, n = re.subn(
        r'mesh body = load\("[^"]*", order: 2\)',
        'mesh body = load("%s", order: %d)' % (os.path.abspath(mesh_path), order),
        src,
    )
    assert n == 1, "mesh line not found in verification_quadratic.soft"
    src, n = re.subn(r"^sim \{", "sim {\n  precision = f64", src, flags=re.M)
    assert n == 1
    src = src.replace("  output vtk every 1 steps\n", "")
    with tempfile.TemporaryDirectory() as tmp:
        script = os.path.join(tmp, "verification.soft")
        with open(script, "w") as f:
            f.write(src)
        t0 = time.time()
        res = subprocess.run(
            [softc, "run", script], cwd=tmp, capture_output=True, text=True
        )
        wall = time.time() - t0
    if res.returncode != 0:
        sys.exit("softc failed:\n" + res.stderr)
    out = json.loads(res.stdout)
    tips = {}
    for scene in out["scenes"]:
        assert scene["solver"]["converged"]
        tips[scene["inputs"]["p_peak"]] = scene["sets"]["tip"]["mean_displacement"][2]
    return tips, wall, out["scenes"][0]["sets"]["tip"]["nodes"]


# ---------------------------------------------------------------------------------------------
# SfePy


def read_msh(path):
    """Vertices (m), tetrahedra and the "cavity" triangles of a gmsh file, unused nodes
    dropped."""
    import meshio

    m = meshio.read(path)
    cav_tag = m.field_data["cavity"][0]
    tets, tris = [], []
    for block, phys in zip(m.cells, m.cell_data["gmsh:physical"]):
        if block.type == "tetra":
            tets.append(block.data)
        elif block.type == "triangle":
            tris.append(block.data[phys == cav_tag])
        else:
            assert block.type in ("vertex", "line"), block.type
    tets = nm.concatenate(tets)
    tris = nm.concatenate(tris)
    used = nm.unique(tets)
    remap = -nm.ones(len(m.points), dtype=nm.int64)
    remap[used] = nm.arange(len(used))
    assert (remap[tris] >= 0).all()
    coors = m.points[used] * 1e-3
    return coors, remap[tets].astype(nm.int32), remap[tris]


def solve_sfepy(mesh_path, order, pressures, n_incr=2):
    from sfepy.base.base import IndexedStruct
    from sfepy.discrete import (
        Equation,
        Equations,
        FieldVariable,
        Function,
        Integral,
        Material,
        Problem,
    )
    from sfepy.discrete.conditions import Conditions, EssentialBC
    from sfepy.discrete.fem import FEDomain, Field, Mesh
    from sfepy.solvers.ls import ScipyDirect
    from sfepy.solvers.nls import Newton
    from sfepy.terms import Term

    coors, tets, cav = read_msh(mesh_path)
    n_vert = len(coors)
    # Vertex group 1: the cavity triangles' vertices (used only to find the cavity facets).
    ngroups = nm.zeros(n_vert, dtype=nm.int32)
    ngroups[nm.unique(cav)] = 1
    mesh = Mesh.from_data(
        "mesh", coors, ngroups, [tets], [nm.zeros(len(tets), dtype=nm.int32)], ["3_4"]
    )
    domain = FEDomain("domain", mesh)
    omega = domain.create_region("Omega", "all")
    surface = domain.create_region("Surface", "vertices of surface", "facet")
    cav_all = domain.create_region("CavAll", "vertices of group 1", "facet")
    cavity = domain.create_region("Cavity", "r.CavAll *f r.Surface", "facet")
    clamp = domain.create_region(
        "Clamp", "vertices in (x < %.17g)" % (CLAMP_X + 1e-12), "facet"
    )

    # The cavity region's facets must be exactly the gmsh "cavity" triangles.
    cmesh = domain.cmesh
    cmesh.setup_connectivity(2, 0)
    f2v = cmesh.get_conn(2, 0)
    got = set()
    for fi in cavity.facets:
        got.add(tuple(sorted(f2v.indices[f2v.offsets[fi] : f2v.offsets[fi + 1]])))
    want = set(tuple(sorted(t)) for t in cav)
    assert got == want and len(want) == len(cav), (len(got), len(want))

    # The clamp: every node with x <= 0.5 mm. The clamp region's DOFs are its vertices and the
    # edges between them; check no mid-edge node with x <= 0.5 mm lies on another edge.
    xs = coors[:, 0]
    assert (xs[xs <= CLAMP_X] == 0.0).all(), "clamp vertices off the plane x = 0"
    assert xs[xs > CLAMP_X].min() > 2 * CLAMP_X, "a mid-edge node outside the clamp region"

    field = Field.from_args("fu", nm.float64, "vector", omega, approx_order=order)
    u = FieldVariable("u", "unknown", field)
    v = FieldVariable("v", "test", field, primary_var_name="u")

    solid = Material(
        "solid",
        K=nm.array([[C10, C20, C30, 1.0, 2.0, 3.0]]),
        kappa=2.0 / D1,
    )
    load = {"p": 0.0}

    def traction_fun(ts, coors, mode=None, **kwargs):
        if mode != "qp":
            return None
        val = nm.tile(load["p"] * nm.eye(3), (coors.shape[0], 1, 1))
        return {"val": val}

    traction = Material("traction", function=Function("traction_fun", traction_fun))

    iv = Integral("iv", order=2)  # the 4-point degree-2 rule
    isurf = Integral("is", order=6)
    t1 = Term.new("dw_tl_he_genyeoh(solid.K, v, u)", iv, omega, solid=solid, v=v, u=u)
    t2 = Term.new(
        "dw_tl_bulk_penalty(solid.kappa, v, u)", iv, omega, solid=solid, v=v, u=u
    )
    t3 = Term.new(
        "dw_tl_surface_traction(traction.val, v, u)",
        isurf,
        cavity,
        traction=traction,
        v=v,
        u=u,
    )
    eqs = Equations([Equation("balance", t1 + t2 + t3)])
    pb = Problem("verification", equations=eqs)
    pb.set_bcs(ebcs=Conditions([EssentialBC("clamp", clamp, {"u.all": 0.0})]))
    nls_status = IndexedStruct()
    nls = Newton(
        {
            "i_max": 25,
            "eps_a": 0.0,  # set below from the load
            "eps_r": 1e-12,
            "eps_mode": "or",
            "lin_red": None,
            "ls_on": 2.0,
        },
        lin_solver=ScipyDirect({}),
        status=nls_status,
    )
    pb.set_solver(nls)

    dof_coors = field.get_coor()
    tip = dof_coors[:, 0] > TIP_X

    results = {}
    state = None
    p_prev = 0.0
    t0 = time.time()
    for p in pressures:
        for k in range(1, n_incr + 1):
            load["p"] = p_prev + (p - p_prev) * k / n_incr
            pb.update_materials(mode="force", verbose=False)
            state = pb.solve(
                state0=None if state is None else state.get_state(),
                update_materials=False,
                save_results=False,
                verbose=False,
            )
            assert nls_status.condition == 0, "Newton did not converge"
            if nls.conf.eps_a == 0.0:
                # The first increment starts at u = 0, where the residual is the load vector
                # of p / n_incr: later increments stop at 1e-11 of that (roundoff is ~1e-13).
                nls.conf.eps_a = 1e-11 * nls_status.err0
        p_prev = p
        uz = state.get_state_parts()["u"].reshape((-1, 3))[:, 2]
        results[p] = uz[tip].mean()
        print(
            "  SfePy order %d, %g kPa: %d Newton its (last increment), |r| %.3e -> %.3e"
            % (
                order,
                p / 1e3,
                nls_status.n_iter,
                nls_status.err0,
                nls_status.err,
            ),
            flush=True,
        )
    wall = time.time() - t0
    return results, wall, int(tip.sum()), field.n_nod * 3


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--softc", default=os.path.join(REPO, "target/release/softc"))
    ap.add_argument(
        "--mesh", nargs="+", default=[os.path.join(REPO, "meshes/bench_1k.msh")]
    )
    ap.add_argument("--order", nargs="+", type=int, default=[1, 2])
    args = ap.parse_args()

    from sfepy.base.base import output

    output.set_output(quiet=os.environ.get("SFEPY_VERBOSE") is None)

    rows = []
    for mesh_path in args.mesh:
        for order in args.order:
            tips_s, wall_s, n_tip_s = run_softc(args.softc, mesh_path, order)
            tips_f, wall_f, n_tip_f, ndof = solve_sfepy(mesh_path, order, PRESSURES)
            print(
                "%s order %d: %d dofs (incl. clamped); tip nodes softc %d, SfePy %d;"
                " wall softc %.1f s, SfePy %.1f s"
                % (
                    os.path.basename(mesh_path),
                    order,
                    ndof,
                    n_tip_s,
                    n_tip_f,
                    wall_s,
                    wall_f,
                ),
                flush=True,
            )
            assert n_tip_s == n_tip_f
            for p in PRESSURES:
                a, b = tips_s[p], tips_f[p]
                rows.append((os.path.basename(mesh_path), order, p, a, b, abs(a - b) / abs(b)))

    print()
    print(
        "%-16s %5s %8s %22s %22s %10s"
        % ("mesh", "order", "p [kPa]", "softc tip z [m]", "SfePy tip z [m]", "rel. diff")
    )
    for mesh, order, p, a, b, r in rows:
        print("%-16s %5d %8g %22.15e %22.15e %10.2e" % (mesh, order, p / 1e3, a, b, r))


if __name__ == "__main__":
    main()
