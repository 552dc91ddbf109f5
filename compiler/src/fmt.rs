//! `softc fmt`: the canonical layout of a script.
//!
//! One declaration or statement per line, two-space indentation in blocks, canonical spacing
//! around operators, numbers and units kept as written. Comments are kept: a comment on its own
//! line stays before the next statement, a comment after code stays at the end of that line,
//! and one blank line between statements is kept where the source had any. Formatting is
//! idempotent and never changes what the script means (the tests check both on every example).

use crate::diag::Diagnostic;
use crate::front::ast::*;

/// Format a script. Fails only if the script does not parse.
pub fn format_source(text: &str) -> Result<String, Diagnostic> {
    let script = crate::front::parse(text)?;
    let mut f = Formatter {
        text,
        comments: scan_comments(text),
        next_comment: 0,
        out: String::new(),
        last_end: 0,
        at_block_start: true,
    };
    f.items(&script.items);
    f.flush_comments(text.len(), 0);
    let mut out = f.out;
    while out.ends_with("\n\n") {
        out.pop();
    }
    if !out.is_empty() && !out.ends_with('\n') {
        out.push('\n');
    }
    Ok(out)
}

struct Comment {
    start: usize,
    end: usize,
    /// Code precedes the comment on its line.
    trailing: bool,
}

/// Find `#` comments outside strings.
fn scan_comments(text: &str) -> Vec<Comment> {
    let bytes = text.as_bytes();
    let mut out = Vec::new();
    let mut i = 0;
    let mut line_has_code = false;
    while i < bytes.len() {
        match bytes[i] {
            b'\n' => line_has_code = false,
            b'#' => {
                let start = i;
                while i < bytes.len() && bytes[i] != b'\n' {
                    i += 1;
                }
                out.push(Comment {
                    start,
                    end: i,
                    trailing: line_has_code,
                });
                continue;
            }
            b'"' => {
                line_has_code = true;
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' && bytes[i] != b'\n' {
                    if bytes[i] == b'\\' {
                        i += 1;
                    }
                    i += 1;
                }
            }
            b' ' | b'\t' | b'\r' => {}
            _ => line_has_code = true,
        }
        i += 1;
    }
    out
}

struct Formatter<'a> {
    text: &'a str,
    comments: Vec<Comment>,
    next_comment: usize,
    out: String,
    /// End of the last source piece emitted (for blank-line detection).
    last_end: usize,
    at_block_start: bool,
}

impl Formatter<'_> {
    fn indent(&mut self, level: usize) {
        for _ in 0..level {
            self.out.push_str("  ");
        }
    }

    fn blank_line_before(&mut self, start: usize) {
        let gap = &self.text[self.last_end.min(start)..start];
        if !self.at_block_start && gap.matches('\n').count() >= 2 {
            self.out.push('\n');
        }
    }

    /// Emit the comments that start before `pos`, each on its own line.
    fn flush_comments(&mut self, pos: usize, level: usize) {
        while let Some(c) = self.comments.get(self.next_comment) {
            if c.start >= pos {
                break;
            }
            let (start, end) = (c.start, c.end);
            self.next_comment += 1;
            self.blank_line_before(start);
            self.indent(level);
            self.out.push_str(self.text[start..end].trim_end());
            self.out.push('\n');
            self.last_end = end;
            self.at_block_start = false;
        }
    }

    /// A comment right after `end` on the same line is appended to the line just written.
    fn trailing_comment(&mut self, end: usize) {
        if let Some(c) = self.comments.get(self.next_comment) {
            let between = &self.text[end.min(c.start)..c.start];
            if c.trailing && c.start >= end && !between.contains('\n') {
                let (start, cend) = (c.start, c.end);
                self.next_comment += 1;
                if self.out.ends_with('\n') {
                    self.out.pop();
                }
                self.out.push_str("  ");
                self.out.push_str(self.text[start..cend].trim_end());
                self.out.push('\n');
                self.last_end = cend;
            }
        }
    }

    fn items(&mut self, items: &[Item]) {
        for item in items {
            self.flush_comments(item.span.start, 0);
            self.blank_line_before(item.span.start);
            self.item(item);
            self.last_end = item.span.end;
            self.at_block_start = false;
            self.trailing_comment(item.span.end);
        }
    }

    fn block(&mut self, stmts: &[Stmt], close: usize, level: usize) {
        if stmts.is_empty() && !self.has_comment_before(close) {
            self.out.push_str("{}\n");
            return;
        }
        self.out.push_str("{\n");
        self.at_block_start = true;
        for s in stmts {
            self.flush_comments(s.span.start, level + 1);
            self.blank_line_before(s.span.start);
            self.indent(level + 1);
            self.stmt(s, level + 1);
            self.out.push('\n');
            self.last_end = s.span.end;
            self.at_block_start = false;
            self.trailing_comment(s.span.end);
        }
        self.flush_comments(close, level + 1);
        self.indent(level);
        self.out.push_str("}\n");
        self.last_end = close;
    }

    fn has_comment_before(&self, pos: usize) -> bool {
        self.comments
            .get(self.next_comment)
            .is_some_and(|c| c.start < pos)
    }

    fn item(&mut self, item: &Item) {
        let close = item.span.end.saturating_sub(1);
        match &item.kind {
            ItemKind::Decl { kind, name, value } => {
                let s = format!("{} {} = {}\n", kind.keyword(), name.name, expr(value));
                self.out.push_str(&s);
            }
            ItemKind::Material(m) => {
                let mut s = format!("material {}", m.name.name);
                if let Some(params) = &m.params {
                    s.push_str(&fn_params(params));
                }
                match &m.body {
                    MaterialBody::Expr(e) => {
                        s.push_str(&format!(" = {}\n", expr(e)));
                        self.out.push_str(&s);
                    }
                    MaterialBody::Block(stmts) => {
                        s.push(' ');
                        self.out.push_str(&s);
                        self.block(stmts, close, 0);
                    }
                }
            }
            ItemKind::Param(p) => {
                let mut s = format!("param {}: {} = {}", p.name.name, ty(&p.ty), expr(&p.init));
                if let Some(b) = &p.bounds {
                    let end = |e: &Option<Expr>| e.as_ref().map_or("..".to_string(), expr);
                    s.push_str(&format!(" in [{}, {}]", end(&b.lower), end(&b.upper)));
                }
                s.push('\n');
                self.out.push_str(&s);
            }
            ItemKind::Input(i) => {
                let s = format!(
                    "input {}: {} from {}\n",
                    i.name.name,
                    ty(&i.ty),
                    expr(&i.source)
                );
                self.out.push_str(&s);
            }
            ItemKind::Let(l) => {
                let s = format!("{}\n", let_decl(l));
                self.out.push_str(&s);
            }
            ItemKind::Fn(f) => {
                let kw = if f.is_controller { "controller" } else { "fn" };
                let mut s = format!("{kw} {}{}", f.name.name, fn_params(&f.params));
                if let Some(r) = &f.ret {
                    s.push_str(&format!(" -> {}", ty(r)));
                }
                s.push_str(&format!(" = {}\n", expr(&f.body)));
                self.out.push_str(&s);
            }
            ItemKind::Sim(stmts) => {
                self.out.push_str("sim ");
                self.block(stmts, close, 0);
            }
            ItemKind::Loss(l) => {
                let mut s = format!("loss = {}", expr(&l.value));
                match &l.when {
                    LossWhen::Default => {}
                    LossWhen::AtEnd(_) => s.push_str(" at end"),
                    LossWhen::Over { from, to, .. } => {
                        s.push_str(&format!(" over [{}, {}]", expr(from), expr(to)))
                    }
                }
                s.push('\n');
                self.out.push_str(&s);
            }
            ItemKind::Optimize(o) => {
                let targets: Vec<&str> = o.targets.iter().map(|t| t.name.as_str()).collect();
                let mut s = format!(
                    "optimize {} with {}",
                    targets.join(", "),
                    expr(&o.optimizer)
                );
                if let Some(n) = &o.iterations {
                    s.push_str(&format!(" for {} iterations", expr(n)));
                }
                match &o.body {
                    None => {
                        s.push('\n');
                        self.out.push_str(&s);
                    }
                    Some(stmts) => {
                        s.push(' ');
                        self.out.push_str(&s);
                        self.block(stmts, close, 0);
                    }
                }
            }
        }
    }

    fn stmt(&mut self, s: &Stmt, _level: usize) {
        let text = match &s.kind {
            StmtKind::Let(l) => let_decl(l),
            StmtKind::Assign { name, value } => format!("{} = {}", name.name, expr(value)),
            StmtKind::Energy { name, args, body } => {
                let args: Vec<&str> = args.iter().map(|a| a.name.as_str()).collect();
                format!("{}({}) = {}", name.name, args.join(", "), expr(body))
            }
            StmtKind::Fix(names) => {
                let names: Vec<&str> = names.iter().map(|n| n.name.as_str()).collect();
                format!("fix {}", names.join(", "))
            }
            StmtKind::Pressure { chamber, value } => {
                format!("pressure {} = {}", chamber.name, expr(value))
            }
            StmtKind::Contact {
                body,
                obstacle,
                args,
            } if args.is_empty() => format!("contact {} with {}", body.name, obstacle.name),
            StmtKind::Contact {
                body,
                obstacle,
                args,
            } => format!(
                "contact {} with {} {}",
                body.name,
                obstacle.name,
                call_args(args)
            ),
            StmtKind::Use { material, set } => match set {
                Some(set) => format!("use {} in {}", material.name, set.name),
                None => format!("use {}", material.name),
            },
            StmtKind::Output { what, every, steps } => format!(
                "output {} every {}{}",
                expr(what),
                expr(every),
                if *steps { " steps" } else { "" }
            ),
            StmtKind::Stop(c) => format!("stop when {}", expr(c)),
            StmtKind::Validate { input, source } => {
                format!("validate {} from {}", input.name, expr(source))
            }
        };
        self.out.push_str(&text);
    }
}

/// `(a, name: b)`.
fn call_args(args: &[Arg]) -> String {
    let args: Vec<String> = args
        .iter()
        .map(|a| match &a.name {
            Some(n) => format!("{}: {}", n.name, expr(&a.value)),
            None => expr(&a.value),
        })
        .collect();
    format!("({})", args.join(", "))
}

fn let_decl(l: &LetDecl) -> String {
    match &l.ty {
        Some(t) => format!("let {}: {} = {}", l.name.name, ty(t), expr(&l.value)),
        None => format!("let {} = {}", l.name.name, expr(&l.value)),
    }
}

fn fn_params(params: &[FnParam]) -> String {
    let ps: Vec<String> = params
        .iter()
        .map(|p| match &p.default {
            Some(d) => format!("{}: {} = {}", p.name.name, ty(&p.ty), expr(d)),
            None => format!("{}: {}", p.name.name, ty(&p.ty)),
        })
        .collect();
    format!("({})", ps.join(", "))
}

fn ty(t: &TypeExpr) -> String {
    let mut s = dim(&t.dim);
    if !t.shape.is_empty() {
        let items: Vec<String> = t
            .shape
            .iter()
            .map(|i| match i {
                ShapeItem::Any(_) => "*".to_string(),
                ShapeItem::Len(n, _) => n.clone(),
                ShapeItem::Set(id) => id.name.clone(),
            })
            .collect();
        s.push_str(&format!("[{}]", items.join(", ")));
    }
    s
}

fn dim(d: &DimExpr) -> String {
    let mut s = dim_factor(&d.first);
    for (op, f) in &d.rest {
        s.push(if *op == DimOp::Mul { '*' } else { '/' });
        s.push_str(&dim_factor(f));
    }
    s
}

fn dim_factor(f: &DimFactor) -> String {
    let mut s = match &f.base {
        DimBase::One => "1".to_string(),
        DimBase::Named(id) => id.name.clone(),
        DimBase::Group(g) => format!("({})", dim(g)),
    };
    if let Some((p, _)) = &f.power {
        s.push('^');
        s.push_str(p);
    }
    s
}

/// Print an expression with canonical spacing. Parentheses are kept as written, so the
/// printed text parses back to the same tree.
pub fn expr(e: &Expr) -> String {
    match &e.kind {
        ExprKind::Number { text, unit, .. } => match unit {
            Some(u) => format!("{text} {u}"),
            None => text.clone(),
        },
        ExprKind::Array { items, unit } => {
            let items: Vec<String> = items.iter().map(expr).collect();
            match unit {
                Some(u) => format!("[{}] {u}", items.join(", ")),
                None => format!("[{}]", items.join(", ")),
            }
        }
        ExprKind::Str(s) => {
            let escaped = s
                .replace('\\', "\\\\")
                .replace('"', "\\\"")
                .replace('\n', "\\n")
                .replace('\t', "\\t");
            format!("\"{escaped}\"")
        }
        ExprKind::Bool(b) => b.to_string(),
        ExprKind::Name(id) => id.name.clone(),
        ExprKind::Paren(inner) => format!("({})", expr(inner)),
        ExprKind::Unary { op, operand } => match op {
            UnaryOp::Neg => format!("-{}", expr(operand)),
            UnaryOp::Not => format!("not {}", expr(operand)),
        },
        ExprKind::Binary { op, lhs, rhs } => match op {
            // `2 mm ^2` squares a quantity; without the space `2 mm^2` is a unit power.
            BinOp::Pow if has_unit(lhs) => format!("{} ^{}", expr(lhs), expr(rhs)),
            BinOp::Pow | BinOp::Range => format!("{}{}{}", expr(lhs), op.symbol(), expr(rhs)),
            _ => format!("{} {} {}", expr(lhs), op.symbol(), expr(rhs)),
        },
        ExprKind::Call { callee, args } => format!("{}{}", expr(callee), call_args(args)),
        ExprKind::Index { base, indices } => {
            let idx: Vec<String> = indices.iter().map(expr).collect();
            format!("{}[{}]", expr(base), idx.join(", "))
        }
        ExprKind::Field { base, field } => format!("{}.{}", expr(base), field.name),
        ExprKind::Reduce {
            op,
            var,
            domain,
            body,
        } => format!(
            "{}({} in {}) {}",
            op.name(),
            var.name,
            expr(domain),
            expr(body)
        ),
        ExprKind::If {
            cond,
            then,
            otherwise,
        } => format!(
            "if {} then {} else {}",
            expr(cond),
            expr(then),
            expr(otherwise)
        ),
    }
}

fn has_unit(e: &Expr) -> bool {
    matches!(
        &e.kind,
        ExprKind::Number { unit: Some(_), .. } | ExprKind::Array { unit: Some(_), .. }
    )
}
