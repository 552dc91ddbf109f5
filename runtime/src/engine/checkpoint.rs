//! Checkpoint schedules for the adjoint pass, as data.
//!
//! The reverse pass needs the state of every step, in reverse order. Storing all of them costs
//! `steps` states of memory; storing a few snapshots and recomputing the states between them
//! trades memory for forward steps. A [`Schedule`] is the list of actions (advance, store,
//! restore, reverse, free) the runtime executes; it starts with state 0 current and nothing
//! stored, and its first reverse action is preceded only by advances and stores — that prefix
//! is the ordinary forward run, which also evaluates the loss.
//!
//! - `store_all`: every state, no recomputation.
//! - `periodic(k)`: every k-th state in the forward run; each segment is recomputed once,
//!   storing its states (memory ≈ steps/k + k states, ≈ 2× the forward steps).
//! - `revolve(s)`: Griewank's binomial schedule with `s` snapshots: with r the least integer
//!   with C(s + r, s) ≥ steps, no step is recomputed more than r times. 4000 steps with 27
//!   snapshots (plus state 0's) cost 2.9 forward runs.

use crate::devices::{HostSlice, HostSliceMut};

/// One action of a schedule. "The current state" is the state in the simulation's buffers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Action {
    /// Step forward from the current state until state `to` is current.
    Advance { to: u64 },
    /// Copy the current state into a slot.
    Store { slot: usize },
    /// Make the state kept in a slot current.
    Restore { slot: usize },
    /// Run the adjoint of step `step` (state `step` → `step + 1`); state `step` is current.
    Reverse { step: u64 },
    /// The slot's state is no longer needed.
    Free { slot: usize },
}

#[derive(Clone, Debug, PartialEq)]
pub struct Schedule {
    pub steps: u64,
    pub actions: Vec<Action>,
    /// The most states stored at once.
    pub slots: usize,
    /// What the schedule is, for reports (`revolve(snapshots: 27)`).
    pub kind: String,
}

/// C(s + r, s): the most steps `s` snapshots reverse with no step advanced more than `r` times.
fn beta(s: u64, r: u64) -> u64 {
    let mut b: u64 = 1;
    for i in 1..=s.min(r) {
        // C(n, i) = C(n, i-1) * (n - i + 1) / i, exact at every step.
        b = b.saturating_mul(s + r - i + 1) / i;
    }
    b
}

struct Writer {
    actions: Vec<Action>,
    current: Option<u64>,
    free: Vec<usize>,
    slot_step: Vec<Option<u64>>,
    in_use: usize,
    max_in_use: usize,
}

impl Writer {
    fn new(slots: usize) -> Self {
        Writer {
            actions: Vec::new(),
            current: Some(0),
            free: (0..slots).rev().collect(),
            slot_step: vec![None; slots],
            in_use: 0,
            max_in_use: 0,
        }
    }

    fn store(&mut self) -> usize {
        let slot = self.free.pop().expect("a free slot");
        self.slot_step[slot] = self.current;
        self.in_use += 1;
        self.max_in_use = self.max_in_use.max(self.in_use);
        self.actions.push(Action::Store { slot });
        slot
    }

    fn free(&mut self, slot: usize) {
        self.slot_step[slot] = None;
        self.in_use -= 1;
        self.free.push(slot);
        self.actions.push(Action::Free { slot });
    }

    /// Make state `to` current, from the slot holding state `from` ≤ `to` if needed.
    fn reach(&mut self, slot: usize, from: u64, to: u64) {
        if !matches!(self.current, Some(c) if c <= to && c >= from) {
            self.actions.push(Action::Restore { slot });
            self.current = Some(from);
        }
        if self.current != Some(to) {
            self.actions.push(Action::Advance { to });
            self.current = Some(to);
        }
    }

    fn reverse(&mut self, step: u64) {
        debug_assert_eq!(self.current, Some(step));
        self.actions.push(Action::Reverse { step });
    }

    /// Reverse steps a..b, state `a` kept in `slot`, every state stored on the way.
    fn store_all(&mut self, a: u64, b: u64, slot: usize) {
        let mut slots = vec![(a, slot)];
        for k in a + 1..b {
            self.reach(slot, a, k);
            slots.push((k, self.store()));
        }
        while let Some((k, s)) = slots.pop() {
            self.reach(s, k, k);
            self.reverse(k);
            if k != a {
                self.free(s);
            }
        }
    }

    /// Reverse steps a..b with state `a` kept in `slot` (binomial splitting).
    fn revolve(&mut self, a: u64, b: u64, slot: usize) {
        let n = b - a;
        if n == 0 {
            return;
        }
        let s = self.free.len() as u64;
        if n == 1 || s + 1 >= n {
            return self.store_all(a, b, slot);
        }
        if s == 0 {
            for k in (a..b).rev() {
                self.reach(slot, a, k);
                self.reverse(k);
                // The next step needs state a again: force a restore.
                self.current = None;
            }
            return;
        }
        let mut r = 1;
        while beta(s, r) < n {
            r += 1;
        }
        // Keep the right part as long as s − 1 snapshots can reverse within r sweeps.
        let left = n.saturating_sub(beta(s - 1, r)).max(1);
        let m = a + left;
        self.reach(slot, a, m);
        let ms = self.store();
        self.revolve(m, b, ms);
        self.free(ms);
        self.revolve(a, m, slot);
    }
}

impl Schedule {
    fn finish(w: Writer, steps: u64, kind: String) -> Schedule {
        Schedule {
            steps,
            actions: w.actions,
            slots: w.max_in_use,
            kind,
        }
    }

    pub fn store_all(steps: u64) -> Schedule {
        let mut w = Writer::new(steps.max(1) as usize);
        if steps > 0 {
            let s0 = w.store();
            w.store_all(0, steps, s0);
            w.free(s0);
        }
        Schedule::finish(w, steps, "store_all".into())
    }

    /// Every `k`-th state stored; each segment recomputed once with its states stored.
    pub fn periodic(steps: u64, k: u64) -> Schedule {
        let k = k.max(1);
        let segments = steps.div_ceil(k);
        let mut w = Writer::new((segments + k) as usize);
        let mut starts = Vec::new();
        for seg in 0..segments {
            w.reach(0, 0, seg * k);
            starts.push((seg * k, w.store()));
        }
        while let Some((a, slot)) = starts.pop() {
            let b = (a + k).min(steps);
            w.store_all(a, b, slot);
            w.free(slot);
        }
        Schedule::finish(w, steps, format!("periodic(steps: {k})"))
    }

    /// The binomial schedule with `snapshots` stored states (at least 1: the initial state).
    pub fn revolve(steps: u64, snapshots: usize) -> Schedule {
        let snapshots = snapshots.max(1);
        let mut w = Writer::new(snapshots);
        if steps > 0 {
            let s0 = w.store();
            w.revolve(0, steps, s0);
            w.free(s0);
        }
        Schedule::finish(w, steps, format!("revolve(snapshots: {snapshots})"))
    }

    /// The fewest snapshots with which no step is recomputed more than 3 times (binomial), at
    /// most `max_snapshots` (the memory budget).
    pub fn auto(steps: u64, max_snapshots: usize) -> Schedule {
        let mut s = 1u64;
        while s < steps && beta(s, 3) < steps {
            s += 1;
        }
        // s free snapshots plus the one holding state 0.
        let s = (s as usize + 1).min(max_snapshots.max(1));
        if s as u64 >= steps {
            let mut sched = Schedule::store_all(steps);
            sched.kind = "auto: store_all".into();
            return sched;
        }
        let mut sched = Schedule::revolve(steps, s);
        sched.kind = format!("auto: {}", sched.kind);
        sched
    }

    /// Forward steps the whole schedule takes, including the forward run.
    pub fn forward_steps(&self) -> u64 {
        let mut current = 0u64;
        let mut slots = std::collections::HashMap::new();
        let mut total = 0;
        for a in &self.actions {
            match *a {
                Action::Advance { to } => {
                    total += to - current;
                    current = to;
                }
                Action::Store { slot } => {
                    slots.insert(slot, current);
                }
                Action::Restore { slot } => current = slots[&slot],
                Action::Reverse { .. } | Action::Free { .. } => {}
            }
        }
        total
    }

    /// Index of the first `Reverse`: the actions before it are the forward run.
    pub fn forward_prefix(&self) -> usize {
        self.actions
            .iter()
            .position(|a| matches!(a, Action::Reverse { .. }))
            .unwrap_or(self.actions.len())
    }
}

/// The states a schedule stores, in one allocation: slot `i` holds the positions and then the
/// velocities of one state (`len` values each) and the step it belongs to, in the device's
/// precision (f32 states are stored as f32: exact, and half the memory).
///
/// One allocation, kept for the process's next backward pass (an optimization's every
/// iteration, a benchmark's repeats), because a fresh page costs a page fault when it is first
/// written, and on the virtual machines these runs are measured on, first touches run at only
/// ~0.4 GB/s: with `store_all` at 10k tets (126 kB a state in f64) they took as long as the
/// steps. The allocation is also asked to be backed by 2 MiB pages where the kernel allows it
/// (Linux `MADV_HUGEPAGE`).
pub struct StateStore {
    data: StoreData,
    len: usize,
    step: Vec<Option<u64>>,
}

enum StoreData {
    F32(Vec<f32>),
    F64(Vec<f64>),
}

/// The largest store of each precision a finished backward pass left, for the next one.
static SPARE: std::sync::Mutex<(Vec<f32>, Vec<f64>)> =
    std::sync::Mutex::new((Vec::new(), Vec::new()));

/// A vector of at least `n` values: the spare one if it is large enough, else a fresh one.
fn take_spare<T: Copy + Default>(spare: &mut Vec<T>, n: usize) -> Vec<T> {
    if spare.len() >= n {
        return std::mem::take(spare);
    }
    // Plain pages: asking for transparent huge pages (MADV_HUGEPAGE) made the kernel compact
    // memory at first touch, which stalled a one-off 10k pass of 3000 steps by 0–0.5 s (its
    // forward 0.34–0.82 s, 0.39–0.41 s without) for ~2 % on the backward once warm.
    vec![T::default(); n]
}

impl StateStore {
    /// Room for `slots` states of `len` positions and `len` velocities each, stored as f32
    /// when `single` (an f32 device's states, exact), else as f64.
    pub fn new(slots: usize, len: usize, single: bool) -> Self {
        let n = slots * 2 * len;
        let mut spare = SPARE.lock().unwrap_or_else(|e| e.into_inner());
        let data = if single {
            StoreData::F32(take_spare(&mut spare.0, n))
        } else {
            StoreData::F64(take_spare(&mut spare.1, n))
        };
        StateStore {
            data,
            len,
            step: vec![None; slots],
        }
    }

    /// Room for state `step` in `slot` (positions, velocities), to be filled by the caller.
    pub fn slot_mut(&mut self, slot: usize, step: u64) -> (HostSliceMut<'_>, HostSliceMut<'_>) {
        let n = self.len;
        let range = slot * 2 * n..(slot + 1) * 2 * n;
        self.step[slot] = Some(step);
        match &mut self.data {
            StoreData::F32(d) => {
                let (x, v) = d[range].split_at_mut(n);
                (HostSliceMut::F32(x), HostSliceMut::F32(v))
            }
            StoreData::F64(d) => {
                let (x, v) = d[range].split_at_mut(n);
                (HostSliceMut::F64(x), HostSliceMut::F64(v))
            }
        }
    }

    /// The step, positions and velocities kept in `slot`, if any, in place.
    pub fn slot(&self, slot: usize) -> Option<(u64, HostSlice<'_>, HostSlice<'_>)> {
        let n = self.len;
        let step = self.step[slot]?;
        let range = slot * 2 * n..(slot + 1) * 2 * n;
        Some(match &self.data {
            StoreData::F32(d) => {
                let (x, v) = d[range].split_at(n);
                (step, HostSlice::F32(x), HostSlice::F32(v))
            }
            StoreData::F64(d) => {
                let (x, v) = d[range].split_at(n);
                (step, HostSlice::F64(x), HostSlice::F64(v))
            }
        })
    }

    pub fn free(&mut self, slot: usize) {
        self.step[slot] = None;
    }
}

impl Drop for StateStore {
    fn drop(&mut self) {
        let mut spare = SPARE.lock().unwrap_or_else(|e| e.into_inner());
        match &mut self.data {
            StoreData::F32(d) if d.len() > spare.0.len() => spare.0 = std::mem::take(d),
            StoreData::F64(d) if d.len() > spare.1.len() => spare.1 = std::mem::take(d),
            _ => {}
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Execute a schedule symbolically: every reverse sees its own state, steps are reversed
    /// exactly once in decreasing order, restores find what was stored.
    fn replay(s: &Schedule) -> u64 {
        let mut current: Option<u64> = Some(0);
        let mut slots: Vec<Option<u64>> = vec![None; s.slots.max(1) * 4 + 8];
        let mut next_reverse = s.steps;
        let mut live = 0usize;
        let mut max_live = 0usize;
        for a in &s.actions {
            match *a {
                Action::Advance { to } => {
                    let c = current.expect("advance from a known state");
                    assert!(to > c, "advance backwards {c} -> {to}");
                    current = Some(to);
                }
                Action::Store { slot } => {
                    assert!(slots[slot].is_none(), "slot {slot} overwritten");
                    slots[slot] = current;
                    live += 1;
                    max_live = max_live.max(live);
                }
                Action::Restore { slot } => current = Some(slots[slot].expect("stored")),
                Action::Free { slot } => {
                    assert!(slots[slot].take().is_some());
                    live -= 1;
                }
                Action::Reverse { step } => {
                    assert_eq!(current, Some(step));
                    assert_eq!(step + 1, next_reverse, "steps reversed in order");
                    next_reverse = step;
                }
            }
        }
        assert_eq!(next_reverse, 0, "every step reversed");
        assert_eq!(live, 0, "every slot freed");
        assert!(max_live <= s.slots);
        s.forward_steps()
    }

    #[test]
    fn schedules_reverse_every_step_once_in_order() {
        for steps in [1u64, 2, 3, 7, 50, 333] {
            replay(&Schedule::store_all(steps));
            for k in [1, 2, 5, 64] {
                replay(&Schedule::periodic(steps, k));
            }
            for s in [1, 2, 3, 5, 20, 400] {
                replay(&Schedule::revolve(steps, s));
            }
            replay(&Schedule::auto(steps, 1000));
        }
    }

    #[test]
    fn binomial_schedule_bounds_memory_and_recomputation() {
        // State 0's snapshot plus 27 free ones: r = 3 sweeps at most (C(30, 3) = 4060 ≥ 4000).
        let s = Schedule::revolve(4000, 28);
        let forward = replay(&s);
        assert!(s.slots <= 28);
        assert!(forward <= 3 * 4000, "{forward}");
        let all = Schedule::store_all(4000);
        assert_eq!(replay(&all), 3999, "store_all never recomputes");
        let p = Schedule::periodic(4000, 64);
        assert!(replay(&p) < 2 * 4000);
        assert!(p.slots <= 63 + 64);
        let auto = Schedule::auto(4000, 1000);
        assert!(auto.slots < 40 && replay(&auto) <= 3 * 4000);
    }

    #[test]
    fn the_forward_run_is_the_prefix() {
        let s = Schedule::revolve(100, 5);
        let p = s.forward_prefix();
        assert!(
            s.actions[..p]
                .iter()
                .all(|a| matches!(a, Action::Advance { .. } | Action::Store { .. }))
        );
        // The prefix reaches the last step's state.
        let last_advance = s.actions[..p].iter().rev().find_map(|a| match a {
            Action::Advance { to } => Some(*to),
            _ => None,
        });
        assert_eq!(last_advance, Some(99));
    }
}
