//! Reverse-mode automatic differentiation of a straight-line body.
//!
//! [`gradient`] appends to a function the instructions that compute the derivatives of one
//! value with respect to others, by one backward sweep over the instructions (the adjoint of
//! each instruction is accumulated in a fixed order, so results are reproducible). Where a
//! derivative does not exist (`abs`, `min`, `max`, comparisons at a tie) the one-sided value of
//! the branch taken is used, as every AD tool does.

use super::{BinOp, Builder, CmpOp, Func, Inst, UnOp, V};

/// Derivatives of `y` with respect to each value in `wrt`, appended to `func`.
pub fn gradient(func: Func, y: V, wrt: &[V]) -> (Func, Vec<V>) {
    let n = y.0 as usize + 1;
    let mut b = Builder::extend(func);
    let mut adj: Vec<Option<V>> = vec![None; n];
    adj[y.0 as usize] = Some(b.constant(1.0));
    let add = |b: &mut Builder, adj: &mut Vec<Option<V>>, v: V, d: V| {
        let slot = &mut adj[v.0 as usize];
        *slot = Some(match *slot {
            Some(acc) => b.add(acc, d),
            None => d,
        });
    };
    for i in (0..n).rev() {
        let Some(g) = adj[i] else { continue };
        let yv = V(i as u32);
        match b.func.insts[i] {
            Inst::Const(_) | Inst::Arg(_) | Inst::Cmp(..) => {}
            Inst::Un(op, a) => {
                let Some(d) = un_chain(&mut b, op, a, yv, g) else {
                    continue;
                };
                add(&mut b, &mut adj, a, d);
            }
            Inst::Bin(op, l, r) => match op {
                BinOp::Add => {
                    add(&mut b, &mut adj, l, g);
                    add(&mut b, &mut adj, r, g);
                }
                BinOp::Sub => {
                    add(&mut b, &mut adj, l, g);
                    let ng = b.neg(g);
                    add(&mut b, &mut adj, r, ng);
                }
                BinOp::Mul => {
                    let dl = b.mul(g, r);
                    let dr = b.mul(g, l);
                    add(&mut b, &mut adj, l, dl);
                    add(&mut b, &mut adj, r, dr);
                }
                BinOp::Div => {
                    let dl = b.div(g, r);
                    let q = b.div(yv, r);
                    let gq = b.mul(g, q);
                    let dr = b.neg(gq);
                    add(&mut b, &mut adj, l, dl);
                    add(&mut b, &mut adj, r, dr);
                }
                BinOp::Pow => {
                    // d(l^r)/dl = r * l^(r-1); with a constant exponent that is all.
                    let dl = match b.func.constant(r) {
                        Some(p) => {
                            let lp = b.powf(l, p - 1.0);
                            let k = b.scale(p, lp);
                            b.mul(g, k)
                        }
                        None => {
                            let one = b.constant(1.0);
                            let rm1 = b.sub(r, one);
                            let lp = b.bin(BinOp::Pow, l, rm1);
                            let k = b.mul(r, lp);
                            b.mul(g, k)
                        }
                    };
                    add(&mut b, &mut adj, l, dl);
                    if b.func.constant(r).is_none() {
                        let ln = b.un(UnOp::Ln, l);
                        let k = b.mul(yv, ln);
                        let dr = b.mul(g, k);
                        add(&mut b, &mut adj, r, dr);
                    }
                }
                BinOp::Min | BinOp::Max => {
                    // The branch taken gets the adjoint (ties go to the left operand).
                    let op = if op == BinOp::Min {
                        CmpOp::Le
                    } else {
                        CmpOp::Ge
                    };
                    let left = b.cmp(op, l, r);
                    let zero = b.constant(0.0);
                    let dl = b.select(left, g, zero);
                    let dr = b.select(left, zero, g);
                    add(&mut b, &mut adj, l, dl);
                    add(&mut b, &mut adj, r, dr);
                }
            },
            Inst::Select(c, l, r) => {
                let zero = b.constant(0.0);
                let dl = b.select(c, g, zero);
                let dr = b.select(c, zero, g);
                add(&mut b, &mut adj, l, dl);
                add(&mut b, &mut adj, r, dr);
            }
        }
    }
    let grads = wrt
        .iter()
        .map(|w| match adj.get(w.0 as usize).copied().flatten() {
            Some(d) => d,
            None => b.constant(0.0),
        })
        .collect();
    (b.finish(), grads)
}

/// `g · f'(a)` for the unary operation y = f(a) (`yv` its value): the factor both sweeps apply
/// to an incoming adjoint or tangent `g`; `None` where f is piecewise constant.
fn un_chain(b: &mut Builder, op: UnOp, a: V, yv: V, g: V) -> Option<V> {
    Some(match op {
        UnOp::Neg => b.neg(g),
        UnOp::Abs => {
            let zero = b.constant(0.0);
            let negative = b.cmp(CmpOp::Lt, a, zero);
            let ng = b.neg(g);
            b.select(negative, ng, g)
        }
        UnOp::Sqrt => {
            let half = b.scale(0.5, g);
            b.div(half, yv)
        }
        UnOp::Cbrt => {
            // d cbrt(a)/da = 1 / (3 cbrt(a)²)
            let y2 = b.mul(yv, yv);
            let d = b.scale(3.0, y2);
            b.div(g, d)
        }
        UnOp::Exp => b.mul(g, yv),
        UnOp::Ln => b.div(g, a),
        UnOp::Sin => {
            let c = b.un(UnOp::Cos, a);
            b.mul(g, c)
        }
        UnOp::Cos => {
            let s = b.un(UnOp::Sin, a);
            let gs = b.mul(g, s);
            b.neg(gs)
        }
        UnOp::Tan => {
            let one = b.constant(1.0);
            let y2 = b.mul(yv, yv);
            let s = b.add(one, y2);
            b.mul(g, s)
        }
        UnOp::Tanh => {
            let one = b.constant(1.0);
            let y2 = b.mul(yv, yv);
            let s = b.sub(one, y2);
            b.mul(g, s)
        }
        UnOp::Floor | UnOp::Ceil => return None,
    })
}

/// Forward-mode derivatives (tangents): given the derivative of some values along one
/// direction (`seeds`: value, its tangent), the derivative of every value up to `upto`
/// (exclusive) along it, appended to `b`. `None` is a structural zero: nothing it depends on
/// is seeded, so no code is generated for it (a unit seed on one corner coordinate touches
/// only what that coordinate reaches). Used for element stiffness matrices (one direction per
/// corner coordinate) and Hessian-vector products; the one-sided rules at kinks are those of
/// [`gradient`].
pub fn tangent(b: &mut Builder, upto: usize, seeds: &[(V, V)]) -> Vec<Option<V>> {
    let mut tan: Vec<Option<V>> = vec![None; upto];
    for &(v, t) in seeds {
        tan[v.0 as usize] = Some(t);
    }
    let zero_or = |b: &mut Builder, t: Option<V>| t.unwrap_or_else(|| b.constant(0.0));
    for i in 0..upto {
        if tan[i].is_some() {
            // A seeded value (an argument) keeps its seed.
            continue;
        }
        let yv = V(i as u32);
        tan[i] = match b.func.insts[i] {
            Inst::Const(_) | Inst::Arg(_) | Inst::Cmp(..) => None,
            Inst::Un(op, a) => {
                let Some(ta) = tan[a.0 as usize] else {
                    continue;
                };
                un_chain(b, op, a, yv, ta)
            }
            Inst::Bin(op, l, r) => {
                let (tl, tr) = (tan[l.0 as usize], tan[r.0 as usize]);
                if tl.is_none() && tr.is_none() {
                    continue;
                }
                match op {
                    BinOp::Add => match (tl, tr) {
                        (Some(a), Some(c)) => Some(b.add(a, c)),
                        (t, None) | (None, t) => t,
                    },
                    BinOp::Sub => match (tl, tr) {
                        (Some(a), Some(c)) => Some(b.sub(a, c)),
                        (Some(a), None) => Some(a),
                        (None, Some(c)) => Some(b.neg(c)),
                        (None, None) => None,
                    },
                    BinOp::Mul => {
                        let a = tl.map(|t| b.mul(t, r));
                        let c = tr.map(|t| b.mul(l, t));
                        match (a, c) {
                            (Some(a), Some(c)) => Some(b.add(a, c)),
                            (t, None) | (None, t) => t,
                        }
                    }
                    BinOp::Div => {
                        // (tl − y·tr) / r
                        let a = tl.map(|t| b.div(t, r));
                        let c = tr.map(|t| {
                            let q = b.div(yv, r);
                            b.mul(t, q)
                        });
                        match (a, c) {
                            (Some(a), Some(c)) => Some(b.sub(a, c)),
                            (Some(a), None) => Some(a),
                            (None, Some(c)) => Some(b.neg(c)),
                            (None, None) => None,
                        }
                    }
                    BinOp::Pow => {
                        let a = tl.map(|t| match b.func.constant(r) {
                            Some(p) => {
                                let lp = b.powf(l, p - 1.0);
                                let k = b.scale(p, lp);
                                b.mul(t, k)
                            }
                            None => {
                                let one = b.constant(1.0);
                                let rm1 = b.sub(r, one);
                                let lp = b.bin(BinOp::Pow, l, rm1);
                                let k = b.mul(r, lp);
                                b.mul(t, k)
                            }
                        });
                        let c = tr.map(|t| {
                            let ln = b.un(UnOp::Ln, l);
                            let k = b.mul(yv, ln);
                            b.mul(t, k)
                        });
                        match (a, c) {
                            (Some(a), Some(c)) => Some(b.add(a, c)),
                            (t, None) | (None, t) => t,
                        }
                    }
                    BinOp::Min | BinOp::Max => {
                        let op = if op == BinOp::Min {
                            CmpOp::Le
                        } else {
                            CmpOp::Ge
                        };
                        let left = b.cmp(op, l, r);
                        let (a, c) = (zero_or(b, tl), zero_or(b, tr));
                        Some(b.select(left, a, c))
                    }
                }
            }
            Inst::Select(c, l, r) => {
                let (tl, tr) = (tan[l.0 as usize], tan[r.0 as usize]);
                if tl.is_none() && tr.is_none() {
                    continue;
                }
                let (a, d) = (zero_or(b, tl), zero_or(b, tr));
                Some(b.select(c, a, d))
            }
        };
    }
    tan
}
