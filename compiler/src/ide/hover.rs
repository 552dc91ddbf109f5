//! Hover texts: declarations with types and units, arguments, built-ins, units and dimensions.

use super::docs::setting_doc;
use super::{
    Analysis, BUILTIN_DOCS, CONSTANT_DOCS, CONTACT_ARGS, CONTACT_DOC, CONTEXTUAL_KEYWORDS, Def,
    DefKind, KEYWORDS, OBSTACLE_SHAPE_DOCS, REDUCTIONS, RESERVED_DOCS, Tok, TokKind,
    opens_contact_args,
};
use crate::front::ast::*;
use crate::sema::types::Ty;
use crate::sema::units::{self, Dim};
use crate::sema::{self, SymKind};

impl Analysis<'_> {
    /// Markdown describing what is at `offset`, and the span it describes.
    pub fn hover(&self, offset: usize) -> Option<(String, Span)> {
        let tok = self.token_at(offset)?;
        let word = &self.text[tok.span.start..tok.span.end];
        match tok.kind {
            TokKind::Unit => return unit_hover(word).map(|h| (h, tok.span)),
            TokKind::Ident => {}
            _ => return None,
        }
        if self.script.is_some() {
            if let Some(def) = self.resolved.def_at(offset) {
                return Some((self.def_hover(def), tok.span));
            }
            if self.resolved.dims.iter().any(|d| d.span == tok.span) {
                return dim_hover(word).map(|h| (h, tok.span));
            }
        } else if let Some((_, kind, span)) =
            self.lexical_decls().into_iter().find(|(n, _, _)| n == word)
        {
            let line_end = self.text[span.start..]
                .find('\n')
                .map_or(self.text.len(), |e| span.start + e);
            let line_start = self.text[..span.start].rfind('\n').map_or(0, |s| s + 1);
            let _ = kind;
            let code = truncate(self.text[line_start..line_end].trim());
            return Some((format!("```soft\n{code}\n```"), tok.span));
        }
        if let Some(h) = self.argument_hover(tok, word) {
            return Some((h, tok.span));
        }
        builtin_hover(word, self.is_call(tok)).map(|h| (h, tok.span))
    }

    /// An argument name (`radius` in `sphere(center: c, radius: 2 mm)`): the callee's parameter.
    fn argument_hover(&self, tok: Tok, word: &str) -> Option<String> {
        let rest = self.text[tok.span.end..].trim_start_matches([' ', '\t']);
        if !rest.starts_with(':') || rest.starts_with("::") {
            return None;
        }
        let callee = self.enclosing_callee(tok.span.start)?;
        if !self.params_of(&callee).iter().any(|p| p == word) {
            return None;
        }
        if callee == CONTACT_ARGS {
            return Some(format!(
                "argument `{word}` of `contact`\n\n```soft\n{}\n```\n\n{}",
                CONTACT_DOC.signature, CONTACT_DOC.doc
            ));
        }
        let sig = BUILTIN_DOCS
            .iter()
            .chain(OBSTACLE_SHAPE_DOCS)
            .find(|b| b.name == callee)
            .map(|b| b.signature.to_string())
            .or_else(|| {
                let item = self
                    .script
                    .as_ref()
                    .and_then(|s| {
                        s.items.iter().find(|i| match &i.kind {
                            ItemKind::Fn(f) => f.name.name == callee,
                            ItemKind::Material(m) => m.name.name == callee,
                            _ => false,
                        })
                    })
                    .map(|i| (self.text, i))
                    .or_else(|| prelude_item(&callee).map(|i| (sema::PRELUDE, i)))?;
                let (text, item) = item;
                Some(match &item.kind {
                    ItemKind::Fn(f) => signature_text(text, item.span, f.body.span),
                    _ => {
                        let t = &text[item.span.start..item.span.end];
                        t[..t.find(['{', '=']).unwrap_or(t.len())]
                            .trim()
                            .to_string()
                    }
                })
            })?;
        Some(format!(
            "argument `{word}` of `{callee}`\n\n```soft\n{}\n```",
            truncate(&sig)
        ))
    }

    /// The name called by the innermost unclosed `(` before `offset`.
    fn enclosing_callee(&self, offset: usize) -> Option<String> {
        let mut depth = 0usize;
        let toks: Vec<&Tok> = self
            .tokens
            .iter()
            .filter(|t| t.span.end <= offset && t.kind != TokKind::Comment)
            .collect();
        for (i, t) in toks.iter().enumerate().rev() {
            if t.kind != TokKind::Punct {
                continue;
            }
            match &self.text[t.span.start..t.span.end] {
                ")" | "]" | "}" => depth += 1,
                "[" | "{" => {
                    if depth == 0 {
                        return None;
                    }
                    depth -= 1;
                }
                "(" => {
                    if depth == 0 {
                        let words: Vec<&str> = toks[i.saturating_sub(4)..i]
                            .iter()
                            .map(|t| &self.text[t.span.start..t.span.end])
                            .collect();
                        if opens_contact_args(&words) {
                            return Some(CONTACT_ARGS.to_string());
                        }
                        let prev = toks.get(i.checked_sub(1)?)?;
                        return (prev.kind == TokKind::Ident)
                            .then(|| self.text[prev.span.start..prev.span.end].to_string());
                    }
                    depth -= 1;
                }
                _ => {}
            }
        }
        None
    }

    fn is_call(&self, tok: Tok) -> bool {
        self.text[tok.span.end..].trim_start().starts_with('(')
    }

    fn def_hover(&self, def: &Def) -> String {
        let text = self.text;
        let src = |s: Span| text.get(s.start..s.end).unwrap_or("");
        let mut code;
        let mut extra = String::new();
        match &def.kind {
            DefKind::Global(kind) => {
                let info = self.global_info(&def.name, def.span);
                let ty_unit = |written: Option<&TypeExpr>| -> String {
                    let ty = info.and_then(|i| i.ty.clone());
                    type_with_unit(ty.as_ref(), written, text)
                };
                let item = self
                    .script
                    .as_ref()
                    .and_then(|s| s.items.iter().find(|i| i.span == def.decl));
                code = match item.map(|i| &i.kind) {
                    Some(ItemKind::Param(p)) => {
                        let mut c = format!(
                            "param {}: {} = {}",
                            def.name,
                            ty_unit(Some(&p.ty)),
                            src(p.init.span)
                        );
                        if let Some(b) = &p.bounds {
                            c.push(' ');
                            c.push_str(src(b.span));
                        }
                        c
                    }
                    Some(ItemKind::Input(i)) => format!(
                        "input {}: {} from {}",
                        def.name,
                        ty_unit(Some(&i.ty)),
                        src(i.source.span)
                    ),
                    Some(ItemKind::Let(l)) => format!(
                        "let {}: {} = {}",
                        def.name,
                        ty_unit(l.ty.as_ref()),
                        src(l.value.span)
                    ),
                    Some(ItemKind::Decl { kind, value, .. }) => {
                        format!("{} {} = {}", kind.keyword(), def.name, src(value.span))
                    }
                    Some(ItemKind::Fn(f)) => signature_text(text, def.decl, f.body.span),
                    Some(ItemKind::Material(m)) => match &m.body {
                        MaterialBody::Expr(e) => {
                            format!("material {} = {}", def.name, src(e.span))
                        }
                        MaterialBody::Block(_) => {
                            let head_end = text[def.decl.start..def.decl.end]
                                .find('{')
                                .map_or(def.decl.end, |i| def.decl.start + i);
                            text[def.decl.start..head_end].trim().to_string()
                        }
                    },
                    _ => format!("{} {}", kind_word(*kind), def.name),
                };
                if let Some(info) = info {
                    if let (Some(v), Some(ty)) = (info.value, &info.ty) {
                        let unit = ty.dim().map(|d| d.si_unit()).unwrap_or_default();
                        let unit = if unit == "1" {
                            String::new()
                        } else {
                            format!(" {unit}")
                        };
                        if !matches!(kind, SymKind::Param) {
                            extra = format!("value: {}{unit} (SI)", fmt_num(v));
                        }
                    } else if let Some(ty) = &info.ty
                        && matches!(ty, Ty::Obj(_))
                    {
                        extra = ty.to_string();
                    }
                }
                let doc = leading_comment(text, def.decl.start);
                if !doc.is_empty() {
                    extra = if extra.is_empty() {
                        doc
                    } else {
                        format!("{extra}\n\n{doc}")
                    };
                }
            }
            DefKind::Param { owner } => {
                code = format!(
                    "{}: {}",
                    def.name,
                    type_with_unit(None, def.ty.as_ref(), text)
                );
                let decl = src(def.decl);
                if let Some(eq) = decl.find('=') {
                    code.push_str(" = ");
                    code.push_str(decl[eq + 1..].trim());
                }
                extra = format!("parameter of `{owner}`");
            }
            DefKind::LocalLet => {
                code = src(def.decl).to_string();
                if let Some(t) = &def.ty {
                    extra = format!("type: {}", type_with_unit(None, Some(t), text));
                }
            }
            DefKind::ReduceVar => {
                let decl = src(def.decl);
                let head = decl.find(')').map_or(decl, |i| &decl[..=i]);
                code = head.to_string();
                extra = format!("`{}`: the variable of this reduction", def.name);
            }
        }
        let code = truncate(&code);
        if extra.is_empty() {
            format!("```soft\n{code}\n```")
        } else {
            format!("```soft\n{code}\n```\n\n{extra}")
        }
    }
}

pub(super) fn kind_word(k: SymKind) -> &'static str {
    match k {
        SymKind::Mesh => "mesh",
        SymKind::Material | SymKind::MaterialTemplate => "material",
        SymKind::Region => "region",
        SymKind::Chamber => "chamber",
        SymKind::Nodes => "nodes",
        SymKind::Elements => "elements",
        SymKind::Obstacle => "obstacle",
        SymKind::Param => "param",
        SymKind::Input => "input",
        SymKind::Let => "let",
        SymKind::Fn => "fn",
        SymKind::Controller => "controller",
    }
}

fn truncate(s: &str) -> String {
    const MAX: usize = 400;
    if s.len() <= MAX {
        return s.to_string();
    }
    let mut end = MAX;
    while !s.is_char_boundary(end) {
        end -= 1;
    }
    format!("{} …", &s[..end])
}

pub(super) fn fmt_num(v: f64) -> String {
    if v != 0.0 && (v.abs() >= 1e15 || v.abs() < 1e-4) {
        format!("{v:e}")
    } else {
        format!("{v}")
    }
}

/// The dimension of a written type (`pressure`, `length/time^2`), when it names only known
/// dimensions.
pub fn eval_dim(d: &DimExpr) -> Option<Dim> {
    fn factor(f: &DimFactor) -> Option<Dim> {
        let base = match &f.base {
            DimBase::One => Dim::NONE,
            DimBase::Named(id) => units::named_dim(&id.name)?,
            DimBase::Group(g) => eval_dim(g)?,
        };
        match &f.power {
            Some((p, _)) => base.powi(p.parse().ok()?),
            None => Some(base),
        }
    }
    let mut acc = factor(&d.first)?;
    for (op, f) in &d.rest {
        let v = factor(f)?;
        acc = match op {
            DimOp::Mul => acc.times(v),
            DimOp::Div => acc.per(v),
        };
    }
    Some(acc)
}

/// `pressure [Pa]`, `length[3] [m]`: a type with its SI unit.
fn type_with_unit(checked: Option<&Ty>, written: Option<&TypeExpr>, text: &str) -> String {
    let written_text =
        written.map(|w| text.get(w.span.start..w.span.end).unwrap_or("").to_string());
    let (name, dim) = match (checked, written) {
        (Some(ty), w) => (
            written_text.clone().unwrap_or_else(|| ty.to_string()),
            ty.dim().or_else(|| w.and_then(|w| eval_dim(&w.dim))),
        ),
        (None, Some(w)) => (written_text.clone().unwrap_or_default(), eval_dim(&w.dim)),
        (None, None) => return "(type not known)".into(),
    };
    match dim {
        Some(d) if !d.is_none() => format!("{name} [{}]", d.si_unit()),
        _ => name,
    }
}

/// The text of a declaration up to its body's `=`: `fn lame_mu(E: pressure, nu: 1) -> pressure`.
fn signature_text(text: &str, decl: Span, body: Span) -> String {
    let head = text.get(decl.start..body.start).unwrap_or("");
    let head = head.trim_end();
    head.strip_suffix('=')
        .unwrap_or(head)
        .trim_end()
        .to_string()
}

/// The `#` comment lines right above `offset`'s line.
fn leading_comment(text: &str, offset: usize) -> String {
    let line_start = text[..offset.min(text.len())]
        .rfind('\n')
        .map_or(0, |i| i + 1);
    let mut lines = Vec::new();
    let mut end = line_start;
    while end > 0 {
        let prev_start = text[..end - 1].rfind('\n').map_or(0, |i| i + 1);
        let line = text[prev_start..end - 1].trim();
        match line.strip_prefix('#') {
            Some(c) => lines.push(c.trim().to_string()),
            None => break,
        }
        end = prev_start;
    }
    lines.reverse();
    lines.join("\n")
}

fn unit_hover(name: &str) -> Option<String> {
    let (factor, dim) = units::unit(name)?;
    let si = dim.si_unit();
    Some(format!(
        "**{name}** — unit of {}\n\n1 {name} = {} {si} (SI)",
        if dim.is_none() {
            "a dimensionless quantity (angle)".to_string()
        } else {
            dim.name()
        },
        fmt_num(factor)
    ))
}

fn dim_hover(name: &str) -> Option<String> {
    let d = units::named_dim(name)?;
    Some(format!("**{name}** — dimension; SI unit `{}`", d.si_unit()))
}

fn prelude() -> Option<&'static Script> {
    static P: std::sync::OnceLock<Option<Script>> = std::sync::OnceLock::new();
    P.get_or_init(|| crate::front::parse(sema::PRELUDE).ok())
        .as_ref()
}

pub(super) fn prelude_item(name: &str) -> Option<&'static Item> {
    prelude()?.items.iter().find(|i| match &i.kind {
        ItemKind::Material(m) => m.name.name == name,
        ItemKind::Fn(f) => f.name.name == name,
        _ => false,
    })
}

/// Names and signatures of the prelude's materials and functions.
pub fn prelude_signatures() -> Vec<(String, String)> {
    let Some(p) = prelude() else {
        return Vec::new();
    };
    p.items
        .iter()
        .filter_map(|i| {
            let (name, body) = match &i.kind {
                ItemKind::Material(m) => (&m.name, None),
                ItemKind::Fn(f) => (&f.name, Some(f.body.span)),
                _ => return None,
            };
            let sig = match body {
                Some(b) => signature_text(sema::PRELUDE, i.span, b),
                None => {
                    let t = &sema::PRELUDE[i.span.start..i.span.end];
                    t[..t.find('{').unwrap_or(t.len())].trim().to_string()
                }
            };
            Some((name.name.clone(), sig))
        })
        .collect()
}

/// Hover text of a built-in name (keyword, function, constant, reserved name, prelude item,
/// dimension, unit).
pub fn builtin_hover(word: &str, called: bool) -> Option<String> {
    if let Some(item) = prelude_item(word) {
        let (sig, what) = match &item.kind {
            ItemKind::Fn(f) => (
                signature_text(sema::PRELUDE, item.span, f.body.span),
                "prelude function",
            ),
            _ => {
                let t = &sema::PRELUDE[item.span.start..item.span.end];
                (t.trim_end().to_string(), "prelude material template")
            }
        };
        let doc = leading_comment(sema::PRELUDE, item.span.start);
        return Some(format!("```soft\n{sig}\n```\n\n{what}. {doc}"));
    }
    let other_meaning = RESERVED_DOCS.iter().any(|(n, _)| *n == word)
        || CONSTANT_DOCS.iter().any(|(n, _)| *n == word);
    if (called || !other_meaning)
        && let Some(b) = BUILTIN_DOCS.iter().find(|b| b.name == word)
    {
        return Some(format!(
            "```soft\n{}\n```\n\nbuilt-in function. {}",
            b.signature, b.doc
        ));
    }
    if let Some(b) = OBSTACLE_SHAPE_DOCS.iter().find(|b| b.name == word) {
        return Some(format!(
            "```soft\n{}\n```\n\nobstacle shape. {}",
            b.signature, b.doc
        ));
    }
    if let Some((_, d)) = RESERVED_DOCS.iter().find(|(n, _)| *n == word) {
        return Some(format!("**{word}** — built-in name: {d}"));
    }
    if let Some((_, d)) = CONSTANT_DOCS.iter().find(|(n, _)| *n == word) {
        return Some(format!("**{word}** — built-in constant: {d}"));
    }
    if let Some((_, d)) = KEYWORDS
        .iter()
        .chain(CONTEXTUAL_KEYWORDS)
        .find(|(n, _)| *n == word)
    {
        return Some(format!("**{word}** — keyword: {d}"));
    }
    if let Some(h) = dim_hover(word) {
        return Some(h);
    }
    if REDUCTIONS.contains(&word) {
        return Some(format!(
            "**{word}** — reduction: `{word}(i in DOMAIN) BODY`"
        ));
    }
    if !setting_doc(word).is_empty() {
        return Some(format!("**{word}** — setting: {}", setting_doc(word)));
    }
    None
}
