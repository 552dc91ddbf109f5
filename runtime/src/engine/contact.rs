//! What the host does for contact with rigid obstacles (the barrier itself is in the compiled
//! node kernels, `softc_compiler::lower::contact`): it fills each contact's node areas and
//! stiffness, refuses a start inside an obstacle, limits every Newton step to stay clear of the
//! obstacles, and reports the contact forces.

use super::{RunError, Simulation};
use crate::devices::Backend;
use crate::text::Sig;
use softc_compiler::driver::{Contact, NO_LIMIT};

/// One contact statement's outcome, for the JSON summary (`solver.contact`).
#[derive(Clone, Debug, Default, PartialEq, serde::Serialize)]
pub struct ContactReport {
    pub body: String,
    pub obstacle: String,
    /// The total force of the obstacle on the body, N.
    pub force: [f64; 3],
    /// Contact nodes within the gap.
    pub active_nodes: usize,
    /// The smallest distance of a contact node from the obstacle, m.
    pub min_distance: f64,
    /// The gap and the contact stiffness the barrier used (Pa; estimated from the materials
    /// when the script gives none).
    pub gap: f64,
    pub stiffness: f64,
}

impl<B: Backend> Simulation<'_, B> {
    fn contacts(&self) -> &[Contact] {
        (self.scene.lowered.contacts.as_ref()).map_or(&[], |c| &c.pairs)
    }

    /// A static solve's refusal of contact on a body its fixed nodes leave free to move
    /// rigidly (`free_motion`, described): frictionless contact does not hold it sideways.
    pub(super) fn refuse_free_contact(&self, free_motion: Option<String>) -> Result<(), RunError> {
        match free_motion {
            Some(motion) if !self.contacts().is_empty() => Err(RunError(format!(
                "this body touches obstacles but is free to move rigidly ({motion}): a static \
                 solve with contact needs fixed nodes that hold it (`fix REGION`), since \
                 frictionless contact does not hold it sideways. Simulate the motion with \
                 `integrator = implicit_euler` or `semi_implicit_euler`"
            ))),
            _ => Ok(()),
        }
    }

    /// Fill the contact buffers and stiffnesses, and refuse a start state (the current
    /// positions, at t = 0) with a node inside an obstacle.
    pub(super) fn prepare_contact(&mut self) -> Result<(), RunError> {
        if self.contacts().is_empty() {
            return Ok(());
        }
        let scene = self.scene;
        for (i, c) in self.contacts().to_vec().iter().enumerate() {
            let mut area = vec![0.0; scene.mesh.nodes.len()];
            if let Some(set) = scene.contact_nodes.get(i) {
                for (&n, &a) in set.nodes.iter().zip(&set.areas) {
                    area[n as usize] = a;
                }
            }
            if area.iter().all(|&a| a == 0.0) {
                return Err(RunError(format!(
                    "`contact {} with {}`: no node of `{}` lies on the mesh's boundary \
                     surface, so nothing can touch the obstacle",
                    c.body, c.obstacle, c.body
                )));
            }
            self.backend.set(c.area, &area);
            let stiffness = match c.stiffness {
                Some(k) => k,
                None => *scene.default_contact_stiffness.get_or_init(|| {
                    // At the script's params: a constant of the scene, which gradients hold.
                    3.0 * super::incompressibility::shear_modulus_at(scene, None).unwrap_or(0.0)
                }),
            };
            if !(stiffness > 0.0 && stiffness.is_finite()) {
                return Err(RunError(format!(
                    "`contact {} with {}`: the materials give no stiffness to scale the \
                     contact barrier with; give one, e.g. `(gap: {} m, stiffness: 100 kPa)`",
                    c.body,
                    c.obstacle,
                    Sig(c.gap)
                )));
            }
            let id = self.uniforms.intern(&c.stiffness_uniform);
            self.uniforms.set(id, stiffness);
        }
        // The rest state must be clear of every obstacle at the start.
        for r in self.contact_report(0.0)? {
            if r.min_distance <= 0.0 {
                return Err(RunError(format!(
                    "`contact {} with {}`: at t = 0 a node of `{}` is {} m inside the obstacle. \
                     A body must start clear of its obstacles: move the obstacle (or the mesh) \
                     so that every surface node is on its free side",
                    r.body,
                    r.obstacle,
                    r.body,
                    Sig(-r.min_distance)
                )));
            }
        }
        Ok(())
    }

    /// The largest α ≤ 1 for which the positions x + α·dx keep every contact node clear of its
    /// obstacle, with a margin (`lower::contact::STEP_FRACTION` of the linearized distance).
    pub(super) fn contact_step_limit(&mut self, dx: &[f64]) -> Result<f64, RunError> {
        let Some(contacts) = &self.scene.lowered.contacts else {
            return Ok(1.0);
        };
        let nodes = 0..self.scene.mesh.nodes.len();
        self.backend.set(contacts.step, dx);
        self.backend
            .run(contacts.step_kernel, nodes, &self.uniforms)
            .map_err(|e| RunError(e.to_string()))?;
        let limit = self.backend.get(contacts.step_limit);
        Ok(limit.iter().fold(1.0f64, |a, &l| a.min(l)))
    }

    /// Each node's contact pressure (Pa) at the current positions and time `t`: the norm of
    /// the obstacles' force on it over its boundary area, summed over the statements; empty
    /// without contact.
    pub(super) fn contact_pressure(&mut self, t: f64) -> Result<Vec<f64>, RunError> {
        if self.contacts().is_empty() {
            return Ok(Vec::new());
        }
        self.contact_report(t)?;
        let mut pressure = vec![0.0; self.scene.mesh.nodes.len()];
        for c in self.contacts().to_vec() {
            let (area, force) = (self.backend.get(c.area), self.backend.get(c.force));
            for (n, p) in pressure.iter_mut().enumerate() {
                if area[n] > 0.0 {
                    let f = &force[3 * n..3 * n + 3];
                    *p += (f[0] * f[0] + f[1] * f[1] + f[2] * f[2]).sqrt() / area[n];
                }
            }
        }
        Ok(pressure)
    }

    /// Each contact's force, active nodes and smallest distance at the current positions and
    /// time `t`.
    pub(super) fn contact_report(&mut self, t: f64) -> Result<Vec<ContactReport>, RunError> {
        let nodes = 0..self.scene.mesh.nodes.len();
        let saved_t = self.uniforms.value(self.ids.t).unwrap_or(0.0);
        self.uniforms.set(self.ids.t, t);
        let mut out = Vec::new();
        for c in self.contacts().to_vec().iter() {
            let ran = (self.backend).run(c.report_kernel, nodes.clone(), &self.uniforms);
            if let Err(e) = ran {
                self.uniforms.set(self.ids.t, saved_t);
                return Err(RunError(e.to_string()));
            }
            let (area, force, distance) = (
                self.backend.get(c.area),
                self.backend.get(c.force),
                self.backend.get(c.distance),
            );
            let id = self.uniforms.intern(&c.stiffness_uniform);
            let stiffness = self.uniforms.value(id).unwrap_or(f64::NAN);
            let mut r = ContactReport {
                body: c.body.clone(),
                obstacle: c.obstacle.clone(),
                min_distance: NO_LIMIT,
                gap: c.gap,
                stiffness,
                ..Default::default()
            };
            for (n, &a) in area.iter().enumerate() {
                if a <= 0.0 {
                    continue;
                }
                for d in 0..3 {
                    r.force[d] += force[3 * n + d];
                }
                r.active_nodes += usize::from(distance[n] < c.gap);
                r.min_distance = r.min_distance.min(distance[n]);
            }
            out.push(r);
        }
        self.uniforms.set(self.ids.t, saved_t);
        Ok(out)
    }
}
