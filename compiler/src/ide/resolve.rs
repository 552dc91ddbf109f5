//! Name resolution over the AST: declarations, their references, and names left free.

use crate::front::ast::*;
use crate::sema::SymKind;
use std::collections::HashMap;

/// What a name refers to.
#[derive(Clone, Debug, PartialEq)]
pub enum DefKind {
    /// A top-level declaration.
    Global(SymKind),
    /// A parameter of a `fn`, `controller` or material template (named by the owner).
    Param { owner: String },
    /// A `let` inside `sim` or a material body.
    LocalLet,
    /// The variable of a reduction (`sum(i in …)`).
    ReduceVar,
}

#[derive(Clone, Debug)]
pub struct Def {
    pub name: String,
    pub kind: DefKind,
    /// The declared name.
    pub span: Span,
    /// The whole declaration (for its text).
    pub decl: Span,
    /// Type as written, if any.
    pub ty: Option<TypeExpr>,
}

/// The declarations and references of one script.
#[derive(Debug, Default)]
pub struct Resolved {
    pub defs: Vec<Def>,
    /// `(use, def index)`.
    pub refs: Vec<(Span, usize)>,
    /// Names used but not declared in the script (built-ins, prelude names, or errors).
    pub free: Vec<Ident>,
    /// Dimension names in types.
    pub dims: Vec<Ident>,
}

struct Resolver {
    r: Resolved,
    globals: HashMap<String, usize>,
    scopes: Vec<HashMap<String, usize>>,
}

/// Resolve the names of a parsed script.
pub fn resolve(script: &Script) -> Resolved {
    let mut rs = Resolver {
        r: Resolved::default(),
        globals: HashMap::new(),
        scopes: Vec::new(),
    };
    for item in &script.items {
        let Some((name, kind)) = SymKind::of_item(item) else {
            continue;
        };
        let ty = match &item.kind {
            ItemKind::Param(p) => Some(p.ty.clone()),
            ItemKind::Input(i) => Some(i.ty.clone()),
            ItemKind::Let(l) => l.ty.clone(),
            ItemKind::Fn(f) => f.ret.clone(),
            _ => None,
        };
        let id = rs.def(name, DefKind::Global(kind), item.span, ty);
        rs.globals.entry(name.name.clone()).or_insert(id);
    }
    for item in &script.items {
        rs.item(item);
    }
    rs.r
}

impl Resolver {
    fn def(&mut self, name: &Ident, kind: DefKind, decl: Span, ty: Option<TypeExpr>) -> usize {
        self.r.defs.push(Def {
            name: name.name.clone(),
            kind,
            span: name.span,
            decl,
            ty,
        });
        self.r.defs.len() - 1
    }

    fn bind(&mut self, name: &Ident, kind: DefKind, decl: Span, ty: Option<TypeExpr>) {
        let id = self.def(name, kind, decl, ty);
        if let Some(s) = self.scopes.last_mut() {
            s.insert(name.name.clone(), id);
        }
    }

    fn use_name(&mut self, id: &Ident) {
        let found = self
            .scopes
            .iter()
            .rev()
            .find_map(|s| s.get(&id.name))
            .or_else(|| self.globals.get(&id.name))
            .copied();
        match found {
            Some(d) => self.r.refs.push((id.span, d)),
            None => self.r.free.push(id.clone()),
        }
    }

    fn ty(&mut self, t: &TypeExpr) {
        self.dim(&t.dim);
        for s in &t.shape {
            if let ShapeItem::Set(id) = s {
                self.use_name(id);
            }
        }
    }

    fn dim(&mut self, d: &DimExpr) {
        for f in std::iter::once(&d.first).chain(d.rest.iter().map(|(_, f)| f)) {
            match &f.base {
                DimBase::One => {}
                DimBase::Named(id) => self.r.dims.push(id.clone()),
                DimBase::Group(g) => self.dim(g),
            }
        }
    }

    fn params(&mut self, owner: &Ident, params: &[FnParam]) {
        for p in params {
            self.ty(&p.ty);
            if let Some(d) = &p.default {
                self.expr(d);
            }
            let decl = p.default.as_ref().map_or(p.ty.span, |d| d.span);
            self.bind(
                &p.name,
                DefKind::Param {
                    owner: owner.name.clone(),
                },
                p.name.span.to(decl),
                Some(p.ty.clone()),
            );
        }
    }

    fn item(&mut self, item: &Item) {
        match &item.kind {
            ItemKind::Decl { value, .. } => self.expr(value),
            ItemKind::Material(m) => {
                self.scopes.push(HashMap::new());
                if let Some(ps) = &m.params {
                    self.params(&m.name, ps);
                }
                match &m.body {
                    MaterialBody::Expr(e) => self.expr(e),
                    MaterialBody::Block(stmts) => self.stmts(stmts),
                }
                self.scopes.pop();
            }
            ItemKind::Param(p) => {
                self.ty(&p.ty);
                self.expr(&p.init);
                if let Some(b) = &p.bounds {
                    for e in b.lower.iter().chain(b.upper.iter()) {
                        self.expr(e);
                    }
                }
            }
            ItemKind::Input(i) => {
                self.ty(&i.ty);
                self.expr(&i.source);
            }
            ItemKind::Let(l) => {
                if let Some(t) = &l.ty {
                    self.ty(t);
                }
                self.expr(&l.value);
            }
            ItemKind::Fn(f) => {
                self.scopes.push(HashMap::new());
                self.params(&f.name, &f.params);
                if let Some(r) = &f.ret {
                    self.ty(r);
                }
                self.expr(&f.body);
                self.scopes.pop();
            }
            ItemKind::Sim(stmts) => {
                self.scopes.push(HashMap::new());
                self.stmts(stmts);
                self.scopes.pop();
            }
            ItemKind::Loss(l) => {
                self.expr(&l.value);
                if let LossWhen::Over { from, to, .. } = &l.when {
                    self.expr(from);
                    self.expr(to);
                }
            }
            ItemKind::Optimize(o) => {
                for t in &o.targets {
                    self.use_name(t);
                }
                self.expr(&o.optimizer);
                if let Some(n) = &o.iterations {
                    self.expr(n);
                }
                if let Some(b) = &o.body {
                    self.stmts(b);
                }
            }
        }
    }

    fn stmts(&mut self, stmts: &[Stmt]) {
        for s in stmts {
            match &s.kind {
                StmtKind::Let(l) => {
                    if let Some(t) = &l.ty {
                        self.ty(t);
                    }
                    self.expr(&l.value);
                    self.bind(&l.name, DefKind::LocalLet, s.span, l.ty.clone());
                }
                StmtKind::Assign { value, .. } => self.expr(value),
                StmtKind::Energy { body, .. } => self.expr(body),
                StmtKind::Fix(names) => names.iter().for_each(|n| self.use_name(n)),
                StmtKind::Pressure { chamber, value } => {
                    self.use_name(chamber);
                    self.expr(value);
                }
                StmtKind::Use { material, set } => {
                    self.use_name(material);
                    if let Some(s) = set {
                        self.use_name(s);
                    }
                }
                StmtKind::Output { what, every, .. } => {
                    self.expr(what);
                    self.expr(every);
                }
                StmtKind::Stop(e) => self.expr(e),
                StmtKind::Validate { input, source } => {
                    self.use_name(input);
                    self.expr(source);
                }
            }
        }
    }

    fn expr(&mut self, e: &Expr) {
        // Iterative over everything but reductions (which open a scope): expressions may be
        // deep, and the parser bounds their depth, so recursion on reductions is fine.
        match &e.kind {
            ExprKind::Name(id) => self.use_name(id),
            ExprKind::Field { base, .. } => self.expr(base),
            ExprKind::Reduce {
                var, domain, body, ..
            } => {
                self.expr(domain);
                self.scopes.push(HashMap::new());
                self.bind(var, DefKind::ReduceVar, e.span, None);
                self.expr(body);
                self.scopes.pop();
            }
            _ => e.for_each_child(|c| self.expr(c)),
        }
    }
}

impl Resolved {
    /// The definition at or referenced at `offset`.
    pub fn def_at(&self, offset: usize) -> Option<&Def> {
        let inside = |s: &Span| s.start <= offset && offset <= s.end;
        if let Some((_, d)) = self.refs.iter().find(|(s, _)| inside(s)) {
            return self.defs.get(*d);
        }
        self.defs.iter().find(|d| inside(&d.span))
    }
}
