//! Update rules (SPEC §8.1), learning-rate schedules and the gradient normalizations of §8.2.
//! Everything acts on the unconstrained values u of the trained entries; the state is plain data
//! so a run can be stopped and resumed bit for bit.

use serde::{Deserialize, Serialize};

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Method {
    Gd,
    Sgd { momentum: f64 },
    Adam { beta1: f64, beta2: f64, eps: f64 },
    Nadam { beta1: f64, beta2: f64, eps: f64 },
}

impl Method {
    pub fn name(&self) -> &'static str {
        match self {
            Method::Gd => "gd",
            Method::Sgd { .. } => "sgd",
            Method::Adam { .. } => "adam",
            Method::Nadam { .. } => "nadam",
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum LrSchedule {
    Constant,
    /// lr·γ^i.
    Exponential {
        gamma: f64,
    },
    /// lr·γ^⌊i/N⌋.
    StepDecay {
        every: u64,
        gamma: f64,
    },
    /// From lr down to floor·lr along half a cosine over the run's iterations.
    Cosine {
        floor: f64,
    },
}

impl LrSchedule {
    /// The learning rate of iteration `i` (from 0) of `n` iterations.
    pub fn at(&self, lr: f64, i: u64, n: u64) -> f64 {
        match *self {
            LrSchedule::Constant => lr,
            LrSchedule::Exponential { gamma } => lr * gamma.powi(i.min(i32::MAX as u64) as i32),
            LrSchedule::StepDecay { every, gamma } => {
                lr * gamma.powi((i / every.max(1)).min(i32::MAX as u64) as i32)
            }
            LrSchedule::Cosine { floor } => {
                let progress = if n <= 1 {
                    0.0
                } else {
                    (i as f64 / (n - 1) as f64).min(1.0)
                };
                lr * (floor + (1.0 - floor) * 0.5 * (1.0 + (std::f64::consts::PI * progress).cos()))
            }
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Normalize {
    None,
    /// Thesis eq. 5.5 with threshold m.
    Magnitude {
        m: f64,
    },
    /// softc's self-tuning scaling (SPEC §8.2).
    Auto,
}

/// What the optimizer remembers between iterations.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MethodState {
    /// Updates taken so far.
    pub step: u64,
    /// First moment (Adam/NAdam) or velocity (SGD with momentum).
    pub m: Vec<f64>,
    /// Second moment (Adam/NAdam).
    pub v: Vec<f64>,
    /// Eq. 5.5's z_g per entry, fixed from the first gradient.
    pub z_g: Vec<Option<f64>>,
    /// `normalize = auto`: running mean of |g| per entry (not bias-corrected) and its weight.
    pub mean_abs_g: Vec<f64>,
    pub mean_weight: f64,
}

impl MethodState {
    pub fn new(n: usize) -> Self {
        MethodState {
            step: 0,
            m: vec![0.0; n],
            v: vec![0.0; n],
            z_g: vec![None; n],
            mean_abs_g: vec![0.0; n],
            mean_weight: 0.0,
        }
    }
}

/// 10^⌊log₁₀ |x|⌋.
fn order_of_magnitude(x: f64) -> f64 {
    10f64.powf(x.abs().log10().floor())
}

/// Smoothing of `normalize = auto`'s running mean of |g|.
const AUTO_DECAY: f64 = 0.8;

/// Scale the gradient (with respect to u) as `normalize` says. `u` are the current values and
/// `natural` each entry's natural size (for `auto`).
pub fn normalize(
    how: Normalize,
    state: &mut MethodState,
    g: &[f64],
    u: &[f64],
    natural: &[f64],
) -> Vec<f64> {
    match how {
        Normalize::None => g.to_vec(),
        Normalize::Magnitude { m } => g
            .iter()
            .zip(u)
            .zip(&mut state.z_g)
            .map(|((&g, &w), z_g)| {
                // Thesis eq. 5.5: z_g from the first gradient (1 where it is zero), z_w from
                // the current value.
                let z_g = *z_g.get_or_insert(if g != 0.0 && g.is_finite() {
                    order_of_magnitude(g)
                } else {
                    1.0
                });
                let z_w = if w.abs() > m {
                    order_of_magnitude(w) / 10.0
                } else {
                    0.1 * m
                };
                g * z_w / z_g
            })
            .collect(),
        Normalize::Auto => {
            // Eq. 5.5 without its two hand-set quantities: the gradient's scale is tracked as
            // it drifts (a running mean of |g| rather than the first gradient's order of
            // magnitude, which the thesis found can go stale), and the target step is a tenth
            // of the entry's natural size instead of m.
            state.mean_weight = AUTO_DECAY * state.mean_weight + (1.0 - AUTO_DECAY);
            g.iter()
                .zip(u)
                .zip(natural)
                .zip(&mut state.mean_abs_g)
                .map(|(((&g, &w), &nat), mean)| {
                    *mean = AUTO_DECAY * *mean + (1.0 - AUTO_DECAY) * g.abs();
                    let scale = *mean / state.mean_weight;
                    if scale == 0.0 || !scale.is_finite() {
                        return 0.0;
                    }
                    g / scale * 0.1 * w.abs().max(nat)
                })
                .collect()
        }
    }
}

/// Clip the global norm to `max` (returns the norm before clipping).
pub fn clip(g: &mut [f64], max: Option<f64>) -> f64 {
    let norm = g.iter().map(|x| x * x).sum::<f64>().sqrt();
    if let Some(max) = max
        && norm > max
    {
        let k = max / norm;
        g.iter_mut().for_each(|x| *x *= k);
    }
    norm
}

/// One update of `u` against the (normalized, clipped) gradient `g` with learning rate `lr`.
pub fn update(method: Method, state: &mut MethodState, u: &mut [f64], g: &[f64], lr: f64) {
    state.step += 1;
    let t = state.step as i32;
    match method {
        Method::Gd => u.iter_mut().zip(g).for_each(|(u, g)| *u -= lr * g),
        Method::Sgd { momentum } => {
            for ((u, g), m) in u.iter_mut().zip(g).zip(&mut state.m) {
                *m = momentum * *m + g;
                *u -= lr * *m;
            }
        }
        Method::Adam { beta1, beta2, eps } | Method::Nadam { beta1, beta2, eps } => {
            let nesterov = matches!(method, Method::Nadam { .. });
            let c1 = 1.0 - beta1.powi(t);
            let c2 = 1.0 - beta2.powi(t);
            for (((u, &g), m), v) in u.iter_mut().zip(g).zip(&mut state.m).zip(&mut state.v) {
                *m = beta1 * *m + (1.0 - beta1) * g;
                *v = beta2 * *v + (1.0 - beta2) * g * g;
                let m_hat = *m / c1;
                let v_hat = *v / c2;
                // NAdam (Dozat 2016): the momentum step looks one step ahead.
                let dir = if nesterov {
                    beta1 * m_hat + (1.0 - beta1) * g / c1
                } else {
                    m_hat
                };
                *u -= lr * dir / (v_hat.sqrt() + eps);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// f(u) = Σ a_i (u_i − c_i)², minimised from u = 0.
    fn minimise(method: Method, lr: f64, iterations: u64) -> (Vec<f64>, Vec<f64>) {
        let a = [1.0, 4.0, 0.25];
        let c = [1.0, -2.0, 3.0];
        let mut u = vec![0.0; 3];
        let mut s = MethodState::new(3);
        for _ in 0..iterations {
            let g: Vec<f64> = (0..3).map(|i| 2.0 * a[i] * (u[i] - c[i])).collect();
            update(method, &mut s, &mut u, &g, lr);
        }
        (u, c.to_vec())
    }

    #[test]
    fn every_method_finds_the_minimum_of_a_quadratic() {
        let adam = Method::Adam {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        };
        let nadam = Method::Nadam {
            beta1: 0.9,
            beta2: 0.999,
            eps: 1e-8,
        };
        for (method, lr, n, tol) in [
            (Method::Gd, 0.1, 600, 1e-6),
            (Method::Sgd { momentum: 0.5 }, 0.05, 600, 1e-6),
            (adam, 0.1, 2000, 1e-3),
            (nadam, 0.1, 2000, 1e-3),
        ] {
            let (u, c) = minimise(method, lr, n);
            for (x, y) in u.iter().zip(&c) {
                assert!((x - y).abs() < tol, "{method:?}: {u:?} vs {c:?}");
            }
        }
    }

    #[test]
    fn gradient_descent_takes_exactly_the_analytic_step() {
        // One step of GD on f = (u − 3)² from 0 with lr 0.25: u = 0 − 0.25·(−6) = 1.5.
        let mut u = vec![0.0];
        let mut s = MethodState::new(1);
        update(Method::Gd, &mut s, &mut u, &[-6.0], 0.25);
        assert_eq!(u, vec![1.5]);
        // Adam's first step has size lr whatever the gradient's scale.
        let mut u = vec![0.0];
        let mut s = MethodState::new(1);
        let adam = Method::Adam {
            beta1: 0.9,
            beta2: 0.999,
            eps: 0.0,
        };
        update(adam, &mut s, &mut u, &[-6e-9], 0.1);
        assert!((u[0] - 0.1).abs() < 1e-12, "{}", u[0]);
    }

    #[test]
    fn eq_5_5_scales_to_one_order_below_the_value() {
        let mut s = MethodState::new(3);
        let how = Normalize::Magnitude { m: 0.1 };
        // First gradient 3.7e-9 → z_g = 1e-9; value 1.0 > m → z_w = 0.1; 0.05 ≤ m → 0.1·m.
        let g = normalize(
            how,
            &mut s,
            &[3.7e-9, -250.0, 0.0],
            &[1.0, 0.05, 2.0],
            &[1.0; 3],
        );
        assert!((g[0] - 0.37).abs() < 1e-12, "{g:?}");
        assert!((g[1] - -2.5 * 0.01).abs() < 1e-12, "{g:?}");
        assert_eq!(g[2], 0.0);
        // z_g stays that of the first gradient; z_w follows the value (now 25 → 1).
        let g = normalize(
            how,
            &mut s,
            &[1e-9, -250.0, 4.0],
            &[25.0, 0.05, 2.0],
            &[1.0; 3],
        );
        assert!((g[0] - 1.0).abs() < 1e-12, "{g:?}");
        // The third entry's first gradient was zero: z_g = 1.
        assert!((g[2] - 4.0 * 0.1).abs() < 1e-12, "{g:?}");
    }

    #[test]
    fn auto_normalization_ignores_the_gradient_scale() {
        // The same history at two scales 12 orders apart gives the same scaled gradients.
        let run = |k: f64| {
            let mut s = MethodState::new(1);
            [1.0, 0.5, 0.8, -0.2]
                .iter()
                .map(|g| normalize(Normalize::Auto, &mut s, &[g * k], &[2.0], &[1.0])[0])
                .collect::<Vec<_>>()
        };
        let (a, b) = (run(1e-9), run(1e3));
        for (x, y) in a.iter().zip(&b) {
            assert!((x - y).abs() < 1e-12 * x.abs().max(1.0), "{a:?} vs {b:?}");
        }
        // The first step is a tenth of the value.
        assert!((a[0] - 0.2).abs() < 1e-12);
    }

    #[test]
    fn clipping_bounds_the_global_norm() {
        let mut g = vec![3.0, 4.0];
        assert_eq!(clip(&mut g, Some(1.0)), 5.0);
        assert!((g[0] - 0.6).abs() < 1e-15 && (g[1] - 0.8).abs() < 1e-15);
        let mut g = vec![0.3, 0.4];
        clip(&mut g, Some(1.0));
        assert_eq!(g, vec![0.3, 0.4]);
    }

    #[test]
    fn schedules() {
        assert_eq!(LrSchedule::Constant.at(0.1, 7, 10), 0.1);
        assert!((LrSchedule::Exponential { gamma: 0.5 }.at(1.0, 3, 10) - 0.125).abs() < 1e-15);
        let s = LrSchedule::StepDecay {
            every: 20,
            gamma: 0.5,
        };
        assert_eq!(s.at(1.0, 19, 100), 1.0);
        assert_eq!(s.at(1.0, 20, 100), 0.5);
        let c = LrSchedule::Cosine { floor: 0.01 };
        assert_eq!(c.at(1.0, 0, 11), 1.0);
        assert!((c.at(1.0, 10, 11) - 0.01).abs() < 1e-15);
        assert!((c.at(1.0, 5, 11) - 0.505).abs() < 1e-12);
    }
}
