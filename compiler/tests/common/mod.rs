//! Shared by the compiler's integration tests: one material of each kind the compiler must
//! differentiate (built-in templates, an any-order series, a user-defined W with Ī2).

pub const MATERIALS: &str = r#"
mesh body = load("m.msh")
material yeoh3 = yeoh(c10: 0.24162 MPa, c20: 0.19977 MPa, c30: -0.00541 MPa, d1: 1.0 /MPa, density: 1070 kg/m^3)
material mr = mooney_rivlin(c10: 0.1 MPa, c01: 0.02 MPa, c11: 0.01 MPa, d1: 2 /MPa, density: 1100 kg/m^3)
material nh = neo_hookean(mu: 0.2 MPa, kappa: 2 MPa, density: 1000 kg/m^3)
material nhln = neo_hookean_ln(mu: lame_mu(0.3 MPa, 0.45), lambda: lame_lambda(0.3 MPa, 0.45), density: 1070 kg/m^3)
material series = yeoh_series(c: [0.24, 0.19, -0.005] MPa, d: [1.0, 3.0] /MPa, density: 1070 kg/m^3)
material custom {
  let k = 1 MPa
  density = 1.2 g/cm^3
  W(I1bar, I2bar, J) = 0.05 MPa * (I1bar - 3)^2 + 0.01 MPa * exp(I2bar - 3) - 0.01 MPa + k / 2 * ln(J)^2
}
material snh = stable_neo_hookean(mu: lame_mu(0.3 MPa, 0.45), lambda: lame_lambda(0.3 MPa, 0.45), density: 1070 kg/m^3)
sim { dt = 1 us; steps = 1; use nh }
"#;

pub const NAMES: [&str; 7] = ["yeoh3", "mr", "nh", "nhln", "series", "custom", "snh"];

/// Signed volume of a tet from its four corners (positive for positive orientation).
pub fn signed_volume(r: [[f64; 3]; 4]) -> f64 {
    let a = [0, 1, 2].map(|k| r[1][k] - r[0][k]);
    let b = [0, 1, 2].map(|k| r[2][k] - r[0][k]);
    let c = [0, 1, 2].map(|k| r[3][k] - r[0][k]);
    (a[0] * (b[1] * c[2] - b[2] * c[1]) - a[1] * (b[0] * c[2] - b[2] * c[0])
        + a[2] * (b[0] * c[1] - b[1] * c[0]))
        / 6.0
}

/// A row of the `rest_shape` buffer: G = Dm⁻¹·Dm⁻ᵀ's upper triangle (G00 G01 G02 G11 G12 G22)
/// and det Dm⁻¹ = 1/det Dm, from this file's own Dm⁻¹ (not the compiler's `rest_shape`).
pub fn rest_shape(r: [[f64; 3]; 4]) -> [f64; 7] {
    let inv = dm_inv(r);
    let g = |a: usize, b: usize| (0..3).map(|k| inv[3 * a + k] * inv[3 * b + k]).sum::<f64>();
    let dm: [[f64; 3]; 3] = [0, 1, 2].map(|row| [0, 1, 2].map(|c| r[c + 1][row] - r[0][row]));
    let det = dm[0][0] * (dm[1][1] * dm[2][2] - dm[1][2] * dm[2][1])
        - dm[0][1] * (dm[1][0] * dm[2][2] - dm[1][2] * dm[2][0])
        + dm[0][2] * (dm[1][0] * dm[2][1] - dm[1][1] * dm[2][0]);
    [
        g(0, 0),
        g(0, 1),
        g(0, 2),
        g(1, 1),
        g(1, 2),
        g(2, 2),
        1.0 / det,
    ]
}

/// Dm⁻¹ row-major, with Dm's columns x1−x0, x2−x0, x3−x0, computed independently of the
/// runtime's precomputation (cofactors over the determinant).
pub fn dm_inv(r: [[f64; 3]; 4]) -> [f64; 9] {
    let m: [[f64; 3]; 3] = [0, 1, 2].map(|row| [0, 1, 2].map(|c| r[c + 1][row] - r[0][row]));
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    let mut inv = [0.0; 9];
    for row in 0..3 {
        for c in 0..3 {
            let (r1, r2) = ((c + 1) % 3, (c + 2) % 3);
            let (c1, c2) = ((row + 1) % 3, (row + 2) % 3);
            inv[3 * row + c] = (m[r1][c1] * m[r2][c2] - m[r1][c2] * m[r2][c1]) / det;
        }
    }
    inv
}
