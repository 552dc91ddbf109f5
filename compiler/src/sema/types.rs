//! Types and compile-time values of checked expressions.

use super::units::Dim;
use std::fmt;

/// One axis of an array shape.
#[derive(Clone, Debug, PartialEq)]
pub enum Len {
    Fixed(usize),
    /// `*` in a template parameter: any length, known at instantiation.
    Any,
    /// One entry per element of the named element set.
    PerElement(String),
}

impl fmt::Display for Len {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Len::Fixed(n) => write!(f, "{n}"),
            Len::Any => f.write_str("*"),
            Len::PerElement(s) => f.write_str(s),
        }
    }
}

/// Kinds of built-in objects that are not numbers.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Obj {
    Mesh,
    Region,
    /// The result of `select`, `named`, `tagged`, `inside`: a node or element set by declaration.
    Selection,
    NodeSet,
    ElementSet,
    Surface,
    /// A rigid obstacle (`plane(…)`, `sphere(…)` in an `obstacle` declaration).
    Obstacle,
    Material,
    MaterialTemplate,
    Optimizer,
    Normalizer,
    Schedule,
    Checkpoint,
    BatchSource,
    OutputKind,
    ForceModel,
    Integrator,
    Precision,
    Auto,
    None,
    /// `x`, `x0`, `v`: per-node state, indexed by a node.
    StateField,
    /// A node bound by `sum(n in set)`.
    Node,
    /// An element bound by `sum(e in set)`.
    Element,
    Range,
}

impl Obj {
    pub fn describe(self) -> &'static str {
        match self {
            Obj::Mesh => "a mesh",
            Obj::Region => "a region",
            Obj::Selection => "a selection",
            Obj::NodeSet => "a node set",
            Obj::ElementSet => "an element set",
            Obj::Surface => "a chamber surface",
            Obj::Obstacle => "an obstacle",
            Obj::Material => "a material",
            Obj::MaterialTemplate => "a material template",
            Obj::Optimizer => "an optimizer",
            Obj::Normalizer => "a gradient normalization",
            Obj::Schedule => "a learning-rate schedule",
            Obj::Checkpoint => "a checkpoint schedule",
            Obj::BatchSource => "a batch source",
            Obj::OutputKind => "an output kind",
            Obj::ForceModel => "a force model",
            Obj::Integrator => "an integrator",
            Obj::Precision => "a precision",
            Obj::Auto => "`auto`",
            Obj::None => "`none`",
            Obj::StateField => "a node state field",
            Obj::Node => "a node",
            Obj::Element => "an element",
            Obj::Range => "a range",
        }
    }
}

#[derive(Clone, Debug, PartialEq)]
pub enum Ty {
    Num {
        dim: Dim,
        shape: Vec<Len>,
        int: bool,
    },
    Bool,
    Str,
    Obj(Obj),
    /// The type of an expression that already produced an error: accepted everywhere so one
    /// mistake gives one diagnostic.
    Error,
}

impl Ty {
    pub fn scalar(dim: Dim) -> Ty {
        Ty::Num {
            dim,
            shape: vec![],
            int: false,
        }
    }
    pub fn int() -> Ty {
        Ty::Num {
            dim: Dim::NONE,
            shape: vec![],
            int: true,
        }
    }
    pub fn vec3(dim: Dim) -> Ty {
        Ty::Num {
            dim,
            shape: vec![Len::Fixed(3)],
            int: false,
        }
    }
    pub fn is_error(&self) -> bool {
        matches!(self, Ty::Error)
    }
    pub fn dim(&self) -> Option<Dim> {
        match self {
            Ty::Num { dim, .. } => Some(*dim),
            _ => None,
        }
    }
    pub fn shape(&self) -> &[Len] {
        match self {
            Ty::Num { shape, .. } => shape,
            _ => &[],
        }
    }
    pub fn is_scalar_num(&self) -> bool {
        matches!(self, Ty::Num { shape, .. } if shape.is_empty())
    }
    pub fn is_int_scalar(&self) -> bool {
        matches!(self, Ty::Num { shape, int: true, dim } if shape.is_empty() && dim.is_none())
    }
}

impl fmt::Display for Ty {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Ty::Num { dim, shape, int } => {
                if *int && dim.is_none() && shape.is_empty() {
                    return f.write_str("integer");
                }
                write!(f, "{}", dim.name())?;
                if !shape.is_empty() {
                    let s: Vec<String> = shape.iter().map(|l| l.to_string()).collect();
                    write!(f, "[{}]", s.join(", "))?;
                }
                Ok(())
            }
            Ty::Bool => f.write_str("bool"),
            Ty::Str => f.write_str("string"),
            Ty::Obj(o) => f.write_str(o.describe()),
            Ty::Error => f.write_str("<error>"),
        }
    }
}

/// How much an expression may change: the checker requires `Const` for geometry and settings
/// and allows the rest in pressures, damping, losses and controllers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Var {
    /// Known when the script is compiled.
    Const,
    /// Depends on trainable parameters or batch inputs, fixed during one simulation.
    Param,
    /// Depends on the time `t`.
    Time,
    /// Depends on the simulation state (positions, velocities).
    State,
}

/// A compile-time value in SI base units.
#[derive(Clone, Debug, PartialEq)]
pub enum Value {
    Num(f64),
    Array(Vec<Value>),
    Bool(bool),
    Str(String),
}

impl Value {
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            Value::Num(v) => Some(*v),
            _ => None,
        }
    }
    /// All numbers in the value, flattened.
    pub fn flatten(&self, out: &mut Vec<f64>) {
        match self {
            Value::Num(v) => out.push(*v),
            Value::Array(items) => items.iter().for_each(|i| i.flatten(out)),
            _ => {}
        }
    }
    pub fn map2(&self, o: &Value, f: &impl Fn(f64, f64) -> f64) -> Option<Value> {
        Some(match (self, o) {
            (Value::Num(a), Value::Num(b)) => Value::Num(f(*a, *b)),
            (Value::Array(a), Value::Array(b)) if a.len() == b.len() => Value::Array(
                a.iter()
                    .zip(b)
                    .map(|(x, y)| x.map2(y, f))
                    .collect::<Option<_>>()?,
            ),
            (Value::Array(a), b @ Value::Num(_)) => {
                Value::Array(a.iter().map(|x| x.map2(b, f)).collect::<Option<_>>()?)
            }
            (a @ Value::Num(_), Value::Array(b)) => {
                Value::Array(b.iter().map(|y| a.map2(y, f)).collect::<Option<_>>()?)
            }
            _ => return None,
        })
    }
    pub fn map(&self, f: &impl Fn(f64) -> f64) -> Option<Value> {
        Some(match self {
            Value::Num(a) => Value::Num(f(*a)),
            Value::Array(a) => Value::Array(a.iter().map(|x| x.map(f)).collect::<Option<_>>()?),
            _ => return None,
        })
    }
}

/// A checked expression: its type, how much it varies, and its value when constant.
#[derive(Clone, Debug)]
pub struct Typed {
    pub ty: Ty,
    pub var: Var,
    pub value: Option<Value>,
}

impl Typed {
    pub fn error() -> Typed {
        Typed {
            ty: Ty::Error,
            var: Var::Const,
            value: None,
        }
    }
    pub fn of(ty: Ty, var: Var) -> Typed {
        Typed {
            ty,
            var,
            value: None,
        }
    }
    pub fn constant(ty: Ty, value: Value) -> Typed {
        Typed {
            ty,
            var: Var::Const,
            value: Some(value),
        }
    }
    pub fn num(&self) -> Option<f64> {
        self.value.as_ref().and_then(Value::as_f64)
    }
}
