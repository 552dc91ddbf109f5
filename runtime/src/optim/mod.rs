//! The optimization loop (SPEC §8): what the `optimize` block asks for ([`Plan`]), the update
//! rules ([`method`]), bounded parameters ([`transform`]), batches of scenes ([`batch`]) and the
//! resumable training loop ([`train`]).

pub mod batch;
pub mod method;
pub mod plot;
pub mod train;
pub mod transform;

use crate::engine::scene::Scene;
use batch::Input;
use method::{LrSchedule, Method, Normalize};
use softc_compiler::driver::{LrScheduleSpec, NormalizeSpec, OptimizerSpec, StopCondition};
use transform::Bounds;

/// Iterations when the block gives neither `for N iterations` nor `stop when`… and also the cap
/// when it only gives `stop when`.
pub const DEFAULT_ITERATIONS: u64 = 100;

/// One trained scalar: an entry of a param.
#[derive(Clone, Debug, PartialEq)]
pub struct Entry {
    /// The uniform it sets (`param.w.1.2`).
    pub uniform: String,
    /// The param it belongs to (`w`).
    pub param: String,
    pub bounds: Bounds,
}

/// The optimize block, evaluated.
#[derive(Clone, Debug)]
pub struct Plan {
    pub entries: Vec<Entry>,
    pub method: Method,
    pub lr: f64,
    pub schedule: LrSchedule,
    pub iterations: u64,
    pub normalize: Normalize,
    pub clip: Option<f64>,
    /// Scenes per iteration.
    pub batch: usize,
    pub seed: u64,
    pub inputs: Vec<Input>,
    /// Scenes the constant inputs enumerate (`None` with only generators or no inputs).
    pub scenes: Option<usize>,
    pub stop: Option<StopCondition>,
    /// `validate INPUT from VALUES`: the input's index and its held-out values.
    pub validate: Option<(usize, Vec<Vec<f64>>)>,
}

impl Plan {
    /// The script's optimize block; `None` without one.
    pub fn from_scene(scene: &Scene) -> Result<Option<Plan>, String> {
        let Some(spec) = &scene.resolved.optimize else {
            return Ok(None);
        };
        // Trained entries, in the order the block lists the params, each in row-major order.
        let mut entries = Vec::new();
        for target in &spec.targets {
            let slots = scene
                .slots_of(target)
                .ok_or_else(|| format!("`{target}` is not a param"))?;
            if slots.uniforms.is_empty() {
                return Err(format!(
                    "the param `{target}` has no entries to train (an empty element set?)"
                ));
            }
            let bounds = Bounds::new(slots.lower, slots.upper);
            for uniform in &slots.uniforms {
                entries.push(Entry {
                    uniform: uniform.clone(),
                    param: target.clone(),
                    bounds,
                });
            }
        }
        let method = match spec.optimizer {
            OptimizerSpec::Gd => Method::Gd,
            OptimizerSpec::Sgd { momentum } => Method::Sgd { momentum },
            OptimizerSpec::Adam { beta1, beta2, eps } => Method::Adam { beta1, beta2, eps },
            OptimizerSpec::Nadam { beta1, beta2, eps } => Method::Nadam { beta1, beta2, eps },
        };
        let schedule = match spec.schedule {
            LrScheduleSpec::Constant => LrSchedule::Constant,
            LrScheduleSpec::Exponential { gamma } => LrSchedule::Exponential { gamma },
            LrScheduleSpec::StepDecay { every, gamma } => LrSchedule::StepDecay { every, gamma },
            LrScheduleSpec::Cosine { floor } => LrSchedule::Cosine { floor },
        };
        let normalize = match spec.normalize {
            NormalizeSpec::None => Normalize::None,
            NormalizeSpec::Auto => Normalize::Auto,
            NormalizeSpec::Magnitude { m } => Normalize::Magnitude { m },
        };
        let inputs = inputs(scene, spec.seed);
        let counts: Vec<(String, usize)> = inputs
            .iter()
            .filter_map(|i| i.count().map(|c| (i.name.clone(), c)))
            .collect();
        if let Some((first, n)) = counts.first()
            && let Some((other, m)) = counts.iter().find(|(_, m)| m != n)
        {
            return Err(format!(
                "the inputs `{first}` ({n} scenes) and `{other}` ({m} scenes) enumerate different \
                 numbers of scenes; give every constant input one value per scene"
            ));
        }
        let scenes = counts.first().map(|(_, n)| *n);
        Ok(Some(Plan {
            entries,
            method,
            lr: spec.lr,
            schedule,
            iterations: spec.iterations.unwrap_or(DEFAULT_ITERATIONS),
            normalize,
            clip: spec.clip,
            batch: spec.batch,
            seed: spec.seed,
            inputs,
            scenes,
            stop: spec.stop.clone(),
            validate: spec.validate.clone(),
        }))
    }

    /// Scenes per iteration (the number of simulations a [`train::Trainer`] needs).
    pub fn scenes_per_iteration(&self) -> usize {
        if self.inputs.is_empty() {
            1
        } else {
            batch::members(self.scenes, self.batch, 0, self.seed, false).len()
        }
    }

    /// Whether the stop condition holds for this iteration's loss and gradient norm.
    pub fn should_stop(
        &self,
        _scene: &Scene,
        loss: f64,
        grad_norm: f64,
        iteration: u64,
    ) -> Result<bool, String> {
        Ok(self
            .stop
            .as_ref()
            .is_some_and(|s| s.holds(loss, grad_norm, iteration)))
    }
}

/// The scenes a plain run (no optimization) covers: one uniform assignment per scene when the
/// script's inputs are constant lists of two or more scenes, else none (the one scene of
/// [`Scene::uniforms`]). A generator input (`circle_quadrants`) has no fixed scenes.
pub fn plain_run_scenes(scene: &Scene) -> Result<Vec<Vec<(String, f64)>>, String> {
    let inputs = inputs(scene, 0);
    let Some(n) = inputs.iter().filter_map(Input::count).max() else {
        return Ok(Vec::new());
    };
    if n < 2 || inputs.iter().any(|i| i.count().is_some_and(|m| m != n)) {
        return Ok(Vec::new());
    }
    Ok((0..n)
        .map(|k| {
            inputs
                .iter()
                .flat_map(|i| {
                    let value = i.value(0, k);
                    i.uniforms.iter().cloned().zip(value).collect::<Vec<_>>()
                })
                .collect()
        })
        .collect())
}

/// The script's inputs with their per-scene values; a generator without its own seed takes
/// `seed` (the optimize block's).
fn inputs(scene: &Scene, seed: u64) -> Vec<Input> {
    scene
        .resolved
        .inputs
        .iter()
        .map(|decl| Input {
            name: decl.name.clone(),
            uniforms: decl.uniforms.clone(),
            source: decl.source.clone(),
            seed,
        })
        .collect()
}
