//! Evaluates a body in f64: the reference semantics every backend must reproduce, and the
//! workhorse of the IR's own tests.

use super::{Func, Inst, eval_bin, eval_cmp, eval_un};

/// Every value of `func` for the given arguments.
pub fn eval_all(func: &Func, args: &[f64]) -> Vec<f64> {
    let mut vals = Vec::with_capacity(func.insts.len());
    eval_into(func, args, &mut vals);
    vals
}

/// Like [`eval_all`], reusing `vals` (cleared first) to avoid an allocation per entity.
pub fn eval_into(func: &Func, args: &[f64], vals: &mut Vec<f64>) {
    assert_eq!(args.len(), func.n_args as usize, "argument count");
    vals.clear();
    for inst in &func.insts {
        let v = |x: super::V| vals[x.0 as usize];
        let r = match *inst {
            Inst::Const(c) => c,
            Inst::Arg(i) => args[i as usize],
            Inst::Un(op, a) => eval_un(op, v(a)),
            Inst::Bin(op, a, b) => eval_bin(op, v(a), v(b)),
            Inst::Cmp(op, a, b) => f64::from(u8::from(eval_cmp(op, v(a), v(b)))),
            Inst::Select(c, a, b) => {
                if v(c) != 0.0 {
                    v(a)
                } else {
                    v(b)
                }
            }
        };
        vals.push(r);
    }
}

/// The outputs of `func` for the given arguments.
pub fn eval(func: &Func, args: &[f64]) -> Vec<f64> {
    let vals = eval_all(func, args);
    func.outputs.iter().map(|o| vals[o.0 as usize]).collect()
}
