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
sim { dt = 1 us; steps = 1; use nh }
"#;

pub const NAMES: [&str; 6] = ["yeoh3", "mr", "nh", "nhln", "series", "custom"];
