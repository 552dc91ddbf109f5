//! Scenes of a batch (SPEC §5.7): each `input` gives one value per scene, from a constant array
//! or from the `circle_quadrants` generator. Sampling is a pure function of (seed, iteration,
//! member), so a resumed run draws exactly the scenes an uninterrupted one would.

pub use softc_compiler::driver::InputSource;

#[derive(Clone, Debug, PartialEq)]
pub struct Input {
    pub name: String,
    /// The uniforms of its entries (`input.target.0` …), in flat order.
    pub uniforms: Vec<String>,
    pub source: InputSource,
    /// The seed of a generator that names none (the optimize block's).
    pub seed: u64,
}

/// SplitMix64: a tiny, well-mixed, stateless-seedable generator.
fn splitmix64(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// A uniform number in [0, 1) from the given stream and draw.
fn uniform(seed: u64, stream: u64, draw: u64) -> f64 {
    let h = splitmix64(seed ^ splitmix64(stream ^ splitmix64(draw)));
    (h >> 11) as f64 / (1u64 << 53) as f64
}

impl Input {
    /// Scenes a constant input enumerates (`None` for a generator).
    pub fn count(&self) -> Option<usize> {
        match &self.source {
            InputSource::Values(v) => Some(v.len()),
            InputSource::CircleQuadrants { .. } => None,
        }
    }

    /// The value of scene `index` (a constant input) or of the `index`-th draw of iteration
    /// `iteration` (a generator: draw i lies in quadrant i mod 4).
    pub fn value(&self, iteration: u64, index: usize) -> Vec<f64> {
        match &self.source {
            InputSource::Values(v) => v[index % v.len()].clone(),
            InputSource::CircleQuadrants {
                radius,
                axes,
                center,
                seed,
            } => {
                let seed = &seed.unwrap_or(self.seed);
                let stream = iteration.wrapping_mul(1 << 20) ^ index as u64;
                let r = radius * uniform(*seed, stream, 0).sqrt();
                let quadrant = (index % 4) as f64;
                let angle = (quadrant + uniform(*seed, stream, 1)) * std::f64::consts::FRAC_PI_2;
                let mut p = *center;
                p[axes[0]] += r * angle.cos();
                p[axes[1]] += r * angle.sin();
                p.to_vec()
            }
        }
    }
}

/// Which scenes iteration `iteration` evaluates, as indices into the inputs' values (or draw
/// numbers of generators), `batch` of them. With constant inputs of `n` scenes: all of them when
/// `batch >= n`, else a mini-batch drawn without replacement (stochastic methods) or the next
/// `batch` in turn (a deterministic sweep for `gd`).
pub fn members(
    n: Option<usize>,
    batch: usize,
    iteration: u64,
    seed: u64,
    shuffle: bool,
) -> Vec<usize> {
    match n {
        None => (0..batch).collect(),
        Some(n) if batch >= n => (0..n).collect(),
        Some(n) if !shuffle => (0..batch)
            .map(|i| (iteration as usize * batch + i) % n)
            .collect(),
        Some(n) => {
            // A partial Fisher–Yates shuffle keyed by the iteration.
            let mut order: Vec<usize> = (0..n).collect();
            for i in 0..batch {
                let j = i + (uniform(seed, iteration, i as u64) * (n - i) as f64) as usize;
                order.swap(i, j.min(n - 1));
            }
            order.truncate(batch);
            order
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn circle_quadrants_puts_one_point_in_each_quadrant_of_the_disc() {
        let input = Input {
            name: "target".into(),
            uniforms: vec![],
            source: InputSource::CircleQuadrants {
                radius: 5e-3,
                axes: [1, 2],
                center: [0.0, 0.0, 0.0],
                seed: Some(7),
            },
            seed: 0,
        };
        for it in 0..50 {
            for q in 0..4 {
                let p = input.value(it, q);
                assert_eq!(p[0], 0.0);
                assert!(p[1].hypot(p[2]) <= 5e-3);
                let (y, z) = (p[1], p[2]);
                let expected = match q {
                    0 => y >= 0.0 && z >= 0.0,
                    1 => y <= 0.0 && z >= 0.0,
                    2 => y <= 0.0 && z <= 0.0,
                    _ => y >= 0.0 && z <= 0.0,
                };
                assert!(expected, "iteration {it} quadrant {q}: {p:?}");
            }
        }
        // Fresh every iteration, identical for the same seed.
        assert_ne!(input.value(0, 0), input.value(1, 0));
        assert_eq!(input.value(3, 2), input.value(3, 2));
    }

    #[test]
    fn mini_batches() {
        assert_eq!(members(Some(3), 5, 0, 1, true), vec![0, 1, 2]);
        assert_eq!(members(None, 4, 9, 1, true), vec![0, 1, 2, 3]);
        assert_eq!(members(Some(5), 2, 1, 1, false), vec![2, 3]);
        let b = members(Some(10), 4, 3, 42, true);
        assert_eq!(b.len(), 4);
        let mut s = b.clone();
        s.sort();
        s.dedup();
        assert_eq!(s.len(), 4, "{b:?}");
        assert_eq!(b, members(Some(10), 4, 3, 42, true));
        // Over many iterations every scene is drawn.
        let mut seen = [false; 10];
        for it in 0..50 {
            for i in members(Some(10), 4, it, 42, true) {
                seen[i] = true;
            }
        }
        assert!(seen.iter().all(|s| *s));
    }
}
