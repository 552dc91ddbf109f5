//! Text form of the IR (`softc compile --emit ir`, golden files).

use super::{ArgSource, BinOp, CmpOp, Domain, Func, Inst, Kernel, Module, UnOp};
use std::fmt::{self, Write};

impl fmt::Display for Module {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for b in &self.buffers {
            writeln!(
                f,
                "buffer {}: {} × {}  # {}",
                b.name,
                domain(b.domain),
                b.width,
                b.doc
            )?;
        }
        for k in &self.kernels {
            writeln!(f)?;
            write_kernel(f, self, k)?;
        }
        Ok(())
    }
}

fn domain(d: Domain) -> &'static str {
    match d {
        Domain::Element => "element",
        Domain::Triangle => "triangle",
        Domain::Node => "node",
        Domain::Single => "single",
    }
}

fn write_kernel(f: &mut fmt::Formatter<'_>, m: &Module, k: &Kernel) -> fmt::Result {
    writeln!(
        f,
        "kernel {} over {}  # {}",
        k.name,
        domain(k.domain),
        k.origin
    )?;
    for (i, a) in k.args.iter().enumerate() {
        let src = match a {
            ArgSource::Own { buffer, component } => {
                format!("{}[self].{component}", m.buffers[buffer.0 as usize].name)
            }
            ArgSource::Corner {
                buffer,
                corner,
                component,
            } => format!(
                "{}[corner {corner}].{component}",
                m.buffers[buffer.0 as usize].name
            ),
            ArgSource::Uniform(u) => format!("uniform {}", m.uniform_name(*u)),
            ArgSource::Gather {
                buffer,
                over,
                stride,
                component,
            } => format!(
                "gather {}[incident {}][corner*{stride} + {component}]",
                m.buffers[buffer.0 as usize].name,
                domain(*over)
            ),
        };
        writeln!(f, "  arg{i} = {src}")?;
    }
    let mut s = String::new();
    write_body(&mut s, &k.body)?;
    f.write_str(&s)?;
    for st in &k.stores {
        writeln!(
            f,
            "  store {}[self].{} = v{}",
            m.buffers[st.buffer.0 as usize].name, st.component, k.body.outputs[st.output].0
        )?;
    }
    Ok(())
}

/// The instructions of a body, one per line.
pub fn write_body(out: &mut String, func: &Func) -> fmt::Result {
    for (i, inst) in func.insts.iter().enumerate() {
        let rhs = match *inst {
            Inst::Const(c) => format!("const {c:e}"),
            Inst::Arg(a) => format!("arg{a}"),
            Inst::Un(op, a) => format!("{} v{}", un(op), a.0),
            Inst::Bin(op, a, b) => format!("{} v{} v{}", bin(op), a.0, b.0),
            Inst::Cmp(op, a, b) => format!("{} v{} v{}", cmp(op), a.0, b.0),
            Inst::Select(c, a, b) => format!("select v{} v{} v{}", c.0, a.0, b.0),
        };
        writeln!(out, "  v{i} = {rhs}")?;
    }
    Ok(())
}

fn un(op: UnOp) -> &'static str {
    match op {
        UnOp::Neg => "neg",
        UnOp::Abs => "abs",
        UnOp::Sqrt => "sqrt",
        UnOp::Cbrt => "cbrt",
        UnOp::Exp => "exp",
        UnOp::Ln => "ln",
        UnOp::Sin => "sin",
        UnOp::Cos => "cos",
        UnOp::Tan => "tan",
        UnOp::Tanh => "tanh",
        UnOp::Floor => "floor",
        UnOp::Ceil => "ceil",
    }
}

fn bin(op: BinOp) -> &'static str {
    match op {
        BinOp::Add => "add",
        BinOp::Sub => "sub",
        BinOp::Mul => "mul",
        BinOp::Div => "div",
        BinOp::Pow => "pow",
        BinOp::Min => "min",
        BinOp::Max => "max",
    }
}

fn cmp(op: CmpOp) -> &'static str {
    match op {
        CmpOp::Lt => "lt",
        CmpOp::Le => "le",
        CmpOp::Gt => "gt",
        CmpOp::Ge => "ge",
        CmpOp::Eq => "eq",
        CmpOp::Ne => "ne",
    }
}
