//! The JSON summary of a run (SI units): the run, each node set's displacement, gradients and
//! the backward pass's report; `softc run --json` and an optimization's `result.json`.

use crate::engine::RunSummary;
use crate::engine::adjoint::GradientReport;
use crate::engine::scene::Scene;
use softc_compiler::driver::{ParamSlots, SlotKind};

/// The JSON summary: SI units throughout.
pub fn summary_json(scene: &Scene, s: &RunSummary, backend: &str) -> serde_json::Value {
    let mut sets = serde_json::Map::new();
    for (name, nodes) in &scene.node_sets {
        let [mean, min, max] = super::set_displacement(nodes, &scene.mesh.nodes, |n| s.x[n]);
        sets.insert(
            name.clone(),
            serde_json::json!({
                "nodes": nodes.len(),
                "mean_displacement": mean,
                "min_displacement": min,
                "max_displacement": max,
            }),
        );
    }
    let motion = crate::engine::Motion::of(scene, s);
    let mut json = serde_json::json!({
        "script": scene.script.display().to_string(),
        "backend": backend,
        "loss": s.loss,
        "steps": s.steps,
        "dt": s.dt,
        "dt_stable_estimate": s.dt_stable_estimate,
        "simulated_time": s.steps as f64 * s.dt,
        "wall_seconds": s.wall_seconds,
        "steps_per_second": s.steps as f64 / s.wall_seconds.max(1e-12),
        "nodes": scene.mesh.nodes.len(),
        "elements": scene.mesh.tets.len(),
        "sets": sets,
        "kinetic_energy": motion.kinetic_energy,
        "max_speed": motion.max_speed,
    });
    if let Some(solver) = &s.solver {
        json["solver"] = serde_json::to_value(solver).unwrap_or_default();
    }
    if !s.contact.is_empty() {
        json["contact"] = serde_json::to_value(&s.contact).unwrap_or_default();
    }
    json["warnings"] = crate::session::run_warnings(scene, s).into();
    json
}

/// The summary of a run over several scenes of the script's inputs: the first scene's summary
/// (without its `inputs`), `loss` the mean of the scenes' losses, and `scenes` each one's
/// summary (with its `inputs`).
pub fn scenes_json(scenes: Vec<serde_json::Value>) -> serde_json::Value {
    let mut json = scenes.first().cloned().unwrap_or_default();
    if let Some(obj) = json.as_object_mut() {
        obj.remove("inputs");
    }
    let losses: Vec<f64> = scenes.iter().filter_map(|r| r["loss"].as_f64()).collect();
    if !losses.is_empty() && losses.len() == scenes.len() {
        json["loss"] = (losses.iter().sum::<f64>() / losses.len() as f64).into();
    }
    json["scenes"] = serde_json::Value::Array(scenes);
    json
}

/// `param.NAME[.i…]` derivatives as `{NAME: number or nested array}`.
pub fn gradients_json(
    slots: &[ParamSlots],
    g: &std::collections::BTreeMap<String, f64>,
) -> serde_json::Value {
    let mut by_param: std::collections::BTreeMap<&str, Vec<(Vec<usize>, f64)>> = Default::default();
    for p in slots.iter().filter(|p| p.kind != SlotKind::Input) {
        for (flat, uniform) in p.uniforms.iter().enumerate() {
            if let Some(d) = g.get(uniform) {
                by_param
                    .entry(&p.name)
                    .or_default()
                    .push((row_major_index(&p.shape, flat), *d));
            }
        }
    }
    fn nest(entries: &[(Vec<usize>, f64)], depth: usize) -> serde_json::Value {
        if entries.len() == 1 && entries[0].0.len() == depth {
            return serde_json::json!(entries[0].1);
        }
        let n = entries.iter().map(|(i, _)| i[depth] + 1).max().unwrap_or(0);
        (0..n)
            .map(|k| {
                let sub: Vec<_> = entries
                    .iter()
                    .filter(|(i, _)| i[depth] == k)
                    .cloned()
                    .collect();
                nest(&sub, depth + 1)
            })
            .collect()
    }
    by_param
        .into_iter()
        .map(|(p, e)| (p.to_string(), nest(&e, 0)))
        .collect::<serde_json::Map<_, _>>()
        .into()
}

/// The index of entry `flat` of a row-major array of `shape` (empty for a scalar).
fn row_major_index(shape: &[usize], flat: usize) -> Vec<usize> {
    let mut index = vec![0; shape.len()];
    let mut rest = flat;
    for (i, n) in shape.iter().enumerate().rev() {
        index[i] = rest % n.max(&1);
        rest /= n.max(&1);
    }
    index
}

/// The backward pass's report: its schedule, the memory it took, its timing and health.
pub fn adjoint_json(g: &GradientReport) -> serde_json::Value {
    serde_json::json!({
        "schedule": g.schedule,
        "stored_states": g.stored_states,
        "state_bytes": g.state_bytes,
        "stored_bytes": g.stored_states * g.state_bytes,
        "recompute_ratio": g.recompute_ratio,
        "reversed_steps": g.reversed_steps,
        "forward_seconds": g.forward_seconds,
        "backward_seconds": g.backward_seconds,
        "growth_per_1000_steps": g.growth_per_1000_steps(),
        "health": g.health.iter().map(|h| serde_json::json!({
            "step": h.step,
            "adj_x_norm": h.adj_x_norm,
            "adj_v_norm": h.adj_v_norm,
        })).collect::<Vec<_>>(),
    })
}
