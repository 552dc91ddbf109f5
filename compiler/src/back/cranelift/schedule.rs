//! The order in which the Cranelift backend emits a kernel body.
//!
//! Cranelift keeps the order it is given (its e-graph pass, which would re-place every pure
//! instruction, is off: see `jit_module_with`), so this order decides how many values are live
//! at once and so how much the register allocator spills (x86 has 16 vector registers; the
//! element kernels' bodies have ~130 operations on ~20 loaded values). The IR's order is kept
//! for the operations, with two changes that shorten live ranges without changing any result:
//!
//! - A buffer argument is loaded just before its first use, not where the IR lists it (all
//!   arguments come first there). A constant is materialized at each use (a constant-pool load
//!   the instruction needs anyway), so it holds no register in between.
//! - A store goes out as soon as its values exist (where the kernel reads no buffer it stores
//!   to, so no later load can see it, and stores each component once, so their order does not
//!   matter), instead of holding every output until the end.
//!
//! The emitted operations are the same as in IR order, so results are the same bits.

use crate::ir::{Func, Inst, operands};

/// One thing to emit.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Step {
    /// The value of the instruction at this index (a constant's again for each use).
    Inst(usize),
    /// The store unit at this index (its values have all been emitted before).
    Store(usize),
}

/// The emission order of `body`. `deferred(i)`: instruction `i` is an argument load or a
/// constant, emitted where it is used. `units[u]`: the values store unit `u` writes.
/// `early_stores`: a unit may go out before the body's last operation.
pub(super) fn order(
    body: &Func,
    deferred: &dyn Fn(usize) -> bool,
    units: &[Vec<usize>],
    early_stores: bool,
) -> Vec<Step> {
    let n = body.insts.len();
    let mut steps = Vec::with_capacity(n + units.len());
    let mut placed = vec![false; n];
    // Emit `u` (if deferred and not yet there) so that it can be read next.
    let ensure = |u: usize, placed: &mut Vec<bool>, steps: &mut Vec<Step>| {
        if !deferred(u) {
            return;
        }
        let constant = matches!(body.insts[u], Inst::Const(_));
        if constant || !placed[u] {
            steps.push(Step::Inst(u));
            placed[u] = true;
        }
    };
    // For each unit, how many of its values are not yet placed (a value may repeat).
    let mut missing: Vec<usize> = units.iter().map(|vs| vs.len()).collect();
    let mut readers: Vec<Vec<usize>> = vec![Vec::new(); n];
    for (u, vs) in units.iter().enumerate() {
        for &v in vs {
            readers[v].push(u);
        }
    }
    let mut stored = vec![false; units.len()];
    let mut place_stores = |v: usize, steps: &mut Vec<Step>| {
        for &u in &readers[v] {
            missing[u] -= 1;
            if missing[u] == 0 && early_stores && !stored[u] {
                steps.push(Step::Store(u));
                stored[u] = true;
            }
        }
    };
    for (i, inst) in body.insts.iter().enumerate() {
        if deferred(i) {
            continue;
        }
        for u in operands(inst) {
            let u = u.0 as usize;
            ensure(u, &mut placed, &mut steps);
        }
        steps.push(Step::Inst(i));
        placed[i] = true;
        place_stores(i, &mut steps);
    }
    // Units of deferred values only (a stored argument or constant), and every unit when
    // stores wait for the end.
    for (u, vs) in units.iter().enumerate() {
        if stored[u] {
            continue;
        }
        for &v in vs {
            ensure(v, &mut placed, &mut steps);
        }
        steps.push(Step::Store(u));
    }
    steps
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ir::Builder;

    /// `out0 = a0 * a1`, `out1 = (a0 + 2) * a2`, stored as two units.
    fn body() -> Func {
        let mut b = Builder::new(3);
        let a0 = b.arg(0);
        let a1 = b.arg(1);
        let a2 = b.arg(2);
        let p = b.mul(a0, a1);
        let two = b.constant(2.0);
        let s = b.add(a0, two);
        let q = b.mul(s, a2);
        let mut f = b.finish();
        f.outputs = vec![p, q];
        f
    }

    fn deferred(f: &Func) -> impl Fn(usize) -> bool + '_ {
        |i| matches!(f.insts[i], Inst::Arg(_) | Inst::Const(_))
    }

    #[test]
    fn loads_come_before_their_first_use_and_stores_after_their_value() {
        let f = body();
        let units = vec![vec![f.outputs[0].0 as usize], vec![f.outputs[1].0 as usize]];
        let steps = order(&f, &deferred(&f), &units, true);
        // a0, a1, a0*a1, store 0, 2, a0+2, a2, (a0+2)*a2, store 1
        assert_eq!(
            steps,
            vec![
                Step::Inst(0),
                Step::Inst(1),
                Step::Inst(3),
                Step::Store(0),
                Step::Inst(4),
                Step::Inst(5),
                Step::Inst(2),
                Step::Inst(6),
                Step::Store(1),
            ]
        );
        // Without early stores both wait for the end.
        let late = order(&f, &deferred(&f), &units, false);
        assert_eq!(late[late.len() - 2..], [Step::Store(0), Step::Store(1)]);
        assert!(!late[..late.len() - 2].contains(&Step::Store(0)));
    }

    #[test]
    fn every_operand_is_emitted_before_it_is_read() {
        let f = body();
        // A unit that stores an argument directly and one that stores a constant.
        let units = vec![vec![2], vec![4, 6]];
        for early in [true, false] {
            let steps = order(&f, &deferred(&f), &units, early);
            let mut have = vec![false; f.insts.len()];
            for s in &steps {
                match *s {
                    Step::Inst(i) => {
                        for u in operands(&f.insts[i]) {
                            assert!(have[u.0 as usize], "{s:?} reads an operand not yet emitted");
                        }
                        have[i] = true;
                    }
                    Step::Store(u) => assert!(units[u].iter().all(|&v| have[v])),
                }
            }
            let stores = steps.iter().filter(|s| matches!(s, Step::Store(_))).count();
            assert_eq!(stores, 2);
        }
    }
}
