//! Physical dimensions and units.
//!
//! A dimension is a vector of exponents over the base quantities mass, length, time and memory
//! (bytes), stored in sixths so `sqrt` and `^(1/3)` of dimensioned values stay exact. Every value
//! is converted to SI base units (kg, m, s) when the script is checked; `softc` never mixes unit
//! systems after that point.

use std::fmt;

const DEN: i16 = 6;

#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Default)]
pub struct Dim(pub [i16; 4]);

impl Dim {
    pub const NONE: Dim = Dim([0; 4]);
    pub const MASS: Dim = Dim([DEN, 0, 0, 0]);
    pub const LENGTH: Dim = Dim([0, DEN, 0, 0]);
    pub const TIME: Dim = Dim([0, 0, DEN, 0]);
    pub const MEMORY: Dim = Dim([0, 0, 0, DEN]);

    /// Exponents beyond ±64: no physical quantity; guards the saturating arithmetic.
    pub fn is_extreme(self) -> bool {
        self.0.iter().any(|e| e.unsigned_abs() > 64 * DEN as u16)
    }
    pub fn is_none(self) -> bool {
        self == Dim::NONE
    }
    pub fn times(self, o: Dim) -> Dim {
        Dim(std::array::from_fn(|i| self.0[i].saturating_add(o.0[i])))
    }
    pub fn per(self, o: Dim) -> Dim {
        Dim(std::array::from_fn(|i| self.0[i].saturating_sub(o.0[i])))
    }
    pub fn inv(self) -> Dim {
        Dim::NONE.per(self)
    }
    pub fn powi(self, p: i32) -> Option<Dim> {
        let mut out = [0i16; 4];
        for (o, e) in out.iter_mut().zip(self.0) {
            *o = i16::try_from(i32::from(e).checked_mul(p)?).ok()?;
        }
        Some(Dim(out))
    }
    /// `self^p` for a real exponent, if every resulting exponent is a whole number of sixths.
    pub fn powf(self, p: f64) -> Option<Dim> {
        let mut out = [0i16; 4];
        for (o, e) in out.iter_mut().zip(self.0) {
            let x = f64::from(e) * p;
            let r = x.round();
            if (x - r).abs() > 1e-9 || r.abs() > f64::from(i16::MAX) {
                return None;
            }
            *o = r as i16;
        }
        Some(Dim(out))
    }

    /// A readable name for the dimension: `pressure`, `length/time`, or base units.
    pub fn name(self) -> String {
        if let Some((n, _)) = NAMED_DIMS.iter().find(|(_, d)| d() == self) {
            return n.to_string();
        }
        if let Some((n, _)) = NAMED_DIMS.iter().find(|(_, d)| d().inv() == self) {
            return format!("1/{n}");
        }
        self.si_unit()
    }

    /// The SI unit of the dimension: `Pa`, `m/s`, `kg*m^-1*s^-2`.
    pub fn si_unit(self) -> String {
        if self.is_none() {
            return "1".into();
        }
        if let Some((_, u)) = SI_NAMES.iter().find(|(d, _)| d() == self) {
            return u.to_string();
        }
        let names = ["kg", "m", "s", "B"];
        let mut parts = Vec::new();
        for (i, e) in self.0.iter().enumerate() {
            if *e == 0 {
                continue;
            }
            let p = if e % DEN == 0 {
                (e / DEN).to_string()
            } else {
                let g = gcd(e.unsigned_abs(), DEN as u16) as i16;
                format!("({}/{})", e / g, DEN / g)
            };
            if p == "1" {
                parts.push(names[i].to_string());
            } else {
                parts.push(format!("{}^{}", names[i], p));
            }
        }
        parts.join("*")
    }
}

fn gcd(a: u16, b: u16) -> u16 {
    if b == 0 { a } else { gcd(b, a % b) }
}

impl fmt::Display for Dim {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(&self.name())
    }
}

fn d(m: i16, l: i16, t: i16) -> Dim {
    Dim([m * DEN, l * DEN, t * DEN, 0])
}

type DimFn = fn() -> Dim;

/// Dimension names usable in types (`param p: pressure`), in display order of preference.
pub const NAMED_DIMS: &[(&str, DimFn)] = &[
    ("dimensionless", || Dim::NONE),
    ("length", || d(0, 1, 0)),
    ("time", || d(0, 0, 1)),
    ("mass", || d(1, 0, 0)),
    ("pressure", || d(1, -1, -2)),
    ("force", || d(1, 1, -2)),
    ("density", || d(1, -3, 0)),
    ("rate", || d(0, 0, -1)),
    ("velocity", || d(0, 1, -1)),
    ("acceleration", || d(0, 1, -2)),
    ("area", || d(0, 2, 0)),
    ("volume", || d(0, 3, 0)),
    ("energy", || d(1, 2, -2)),
    ("memory", || Dim::MEMORY),
    // Aliases: accepted in types, never chosen for display (an earlier entry matches first).
    ("stress", || d(1, -1, -2)),
    ("frequency", || d(0, 0, -1)),
    ("angle", || Dim::NONE),
];

const SI_NAMES: &[(DimFn, &str)] = &[
    (|| d(0, 1, 0), "m"),
    (|| d(0, 0, 1), "s"),
    (|| d(1, 0, 0), "kg"),
    (|| d(1, -1, -2), "Pa"),
    (|| d(1, 1, -2), "N"),
    (|| d(1, -3, 0), "kg/m^3"),
    (|| d(0, 0, -1), "1/s"),
    (|| d(0, 1, -1), "m/s"),
    (|| d(0, 1, -2), "m/s^2"),
    (|| d(0, 2, 0), "m^2"),
    (|| d(0, 3, 0), "m^3"),
    (|| d(1, 2, -2), "J"),
    (|| d(-1, 1, 2), "1/Pa"),
    (|| Dim::MEMORY, "B"),
];

pub fn named_dim(name: &str) -> Option<Dim> {
    NAMED_DIMS
        .iter()
        .find(|(n, _)| *n == name)
        .map(|(_, d)| d())
}

/// Units accepted after a number: name → (factor to SI, dimension).
pub fn unit(name: &str) -> Option<(f64, Dim)> {
    let m = d(0, 1, 0);
    let s = d(0, 0, 1);
    let kg = d(1, 0, 0);
    let pa = d(1, -1, -2);
    let n = d(1, 1, -2);
    Some(match name {
        "m" => (1.0, m),
        "cm" => (1e-2, m),
        "mm" => (1e-3, m),
        "um" | "µm" | "μm" => (1e-6, m),
        "nm" => (1e-9, m),
        "s" => (1.0, s),
        "ms" => (1e-3, s),
        "us" | "µs" | "μs" => (1e-6, s),
        "ns" => (1e-9, s),
        "kg" => (1.0, kg),
        "g" => (1e-3, kg),
        "mg" => (1e-6, kg),
        "N" => (1.0, n),
        "mN" => (1e-3, n),
        "kN" => (1e3, n),
        "Pa" => (1.0, pa),
        "kPa" => (1e3, pa),
        "MPa" => (1e6, pa),
        "GPa" => (1e9, pa),
        "bar" => (1e5, pa),
        "mbar" => (1e2, pa),
        "psi" => (6894.757293168361, pa),
        "Hz" => (1.0, d(0, 0, -1)),
        "kHz" => (1e3, d(0, 0, -1)),
        "rad" => (1.0, Dim::NONE),
        "deg" => (std::f64::consts::PI / 180.0, Dim::NONE),
        "B" => (1.0, Dim::MEMORY),
        "kB" => (1e3, Dim::MEMORY),
        "MB" => (1e6, Dim::MEMORY),
        "GB" => (1e9, Dim::MEMORY),
        "KiB" => (1024.0, Dim::MEMORY),
        "MiB" => (1024.0 * 1024.0, Dim::MEMORY),
        "GiB" => (1024.0 * 1024.0 * 1024.0, Dim::MEMORY),
        _ => return None,
    })
}

pub const UNIT_NAMES: &[&str] = &[
    "m", "cm", "mm", "um", "µm", "nm", "s", "ms", "us", "µs", "ns", "kg", "g", "mg", "N", "mN",
    "kN", "Pa", "kPa", "MPa", "GPa", "bar", "mbar", "psi", "Hz", "kHz", "rad", "deg", "B", "kB",
    "MB", "GB", "KiB", "MiB", "GiB",
];

/// Hints for common unit mistakes, checked before generic "did you mean".
pub fn unit_hint(name: &str) -> Option<&'static str> {
    Some(match name {
        "kpa" | "KPa" | "Kpa" => "kilopascal is written `kPa`",
        "mpa" | "Mpa" => "megapascal is written `MPa`",
        "pa" => "pascal is written `Pa`",
        "sec" | "secs" | "seconds" => "seconds are written `s`",
        "msec" => "milliseconds are written `ms`",
        "MM" | "Mm" => "millimetres are written `mm`",
        "J" => "energy has no unit name in .soft; write `N*m`",
        "l" | "L" | "ml" | "mL" => "volumes are written with lengths, e.g. `mm^3`",
        "min" | "h" => "write durations in `s` or `ms`",
        "dakPa" => "write the pressure in `kPa` (1 dakPa = 10 kPa)",
        _ => return None,
    })
}

/// Parse a value with its unit (`2.5kPa`, `20 us`) with the language's own front end: the
/// value in SI units and its dimension.
pub fn parse_quantity(text: &str) -> Result<(f64, Dim), String> {
    use crate::front::ast::{ExprKind, Item, ItemKind, UnaryOp};
    let src = format!("let __value = {text}");
    let ast = crate::front::parse(&src).map_err(|d| format!("`{text}`: {}", d.message))?;
    let Some(Item {
        kind: ItemKind::Let(l),
        ..
    }) = ast.items.first()
    else {
        return Err(format!("`{text}` is not a value"));
    };
    // A leading minus sign: `-3kPa` (the grammar reads it as negation of `3kPa`).
    let (value_expr, sign) = match &l.value.kind {
        ExprKind::Unary {
            op: UnaryOp::Neg,
            operand,
        } => (&**operand, -1.0),
        _ => (&l.value, 1.0),
    };
    let (num, dim) = match &value_expr.kind {
        ExprKind::Number { value, unit, .. } => {
            let mut factor = 1.0;
            let mut dim = Dim::NONE;
            for f in unit.iter().flat_map(|u| &u.factors) {
                let (k, d) = self::unit(&f.name)
                    .ok_or_else(|| format!("unknown unit `{}` in `{text}`", f.name))?;
                factor *= k.powi(f.power);
                dim = dim.times(d.powi(f.power).unwrap_or(d));
            }
            (sign * value * factor, dim)
        }
        _ => return Err(format!("`{text}` is not a number with a unit")),
    };
    Ok((num, dim))
}
