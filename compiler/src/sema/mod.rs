//! Semantic analysis: name resolution, types, dimensional analysis, parameter bounds, settings,
//! and everything else a user can get wrong in a script that parses.
//!
//! The checker walks the prelude (built-in materials written in .soft) and then the user's
//! script. Global declarations may appear in any order; each is checked on first use, and a
//! declaration defined through itself is reported. Every problem becomes a [`Diagnostic`]; one
//! mistake gives one diagnostic, because a failed expression gets the `Error` type, which is
//! accepted everywhere.

mod builtins;
mod contact;
mod expr;
pub mod hir;
mod items;
pub mod mesh_probe;
mod optimize;
pub mod resolution;
mod sim;
pub mod types;
pub mod units;

pub use builtins::{CONSTANTS, FUNCTIONS};
pub use items::{OPTIMIZE_SETTINGS, SIM_SETTINGS};
pub use resolution::{Def, DefKind, Resolution};

use crate::diag::{Diagnostic, did_you_mean};
use crate::front::ast::{Item, Script, Span};
use std::collections::HashMap;
use std::path::PathBuf;
use types::{Ty, Typed, Var};

/// The prelude's source: built-in materials and helper functions.
pub const PRELUDE: &str = include_str!("prelude.soft");

/// What the checker learned about a script (consumed by lowering in later stages).
#[derive(Debug, Default, Clone)]
pub struct CheckedScript {
    /// Declared parameters in source order: name, type, initial value (SI, flattened).
    pub params: Vec<ParamInfo>,
    /// The simulated duration in seconds, when the script fixes it.
    pub duration: Option<f64>,
    /// The script's global declarations with their checked types (editors: hover).
    pub globals: Vec<GlobalInfo>,
    /// Every declaration and every use of a name with what it resolved to (editors: hover,
    /// definition, references).
    pub resolution: Resolution,
    /// What the script refers to in its mesh, evaluated once (binding reads it).
    pub(crate) mesh_refs: mesh_probe::MeshRefs,
    /// The checked program: declarations by id, names resolved, expressions typed (lowering
    /// and the driver read it, not the syntax tree).
    pub program: hir::Program,
}

/// A global declaration of the user's script, as the checker saw it.
#[derive(Debug, Clone)]
pub struct GlobalInfo {
    pub name: String,
    pub kind: SymKind,
    /// The declared name.
    pub span: Span,
    /// The checked type; `None` when the declaration had an error or was not checked.
    pub ty: Option<types::Ty>,
    /// The compile-time value in SI units, when it is a known scalar.
    pub value: Option<f64>,
}

#[derive(Debug, Clone)]
pub struct ParamInfo {
    pub name: String,
    pub ty: Ty,
    pub init: Vec<f64>,
    pub lower: Option<f64>,
    pub upper: Option<f64>,
}

/// Options for checking: where relative paths (meshes) are resolved, and how meshes are read.
#[derive(Default, Clone)]
pub struct CheckOptions {
    /// Directory of the script; `None` skips file-existence checks (editors, fuzzing).
    pub base_dir: Option<PathBuf>,
    /// Reads the mesh so surfaces, tags and selections can be checked against it.
    pub mesh_probe: Option<std::sync::Arc<dyn mesh_probe::MeshProbe>>,
}

impl std::fmt::Debug for CheckOptions {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CheckOptions")
            .field("base_dir", &self.base_dir)
            .field("mesh_probe", &self.mesh_probe.is_some())
            .finish()
    }
}

/// Check a parsed script. Diagnostics come back sorted by position.
pub fn check(script: &Script, options: &CheckOptions) -> (CheckedScript, Vec<Diagnostic>) {
    let prelude = prelude_ast();
    let mut c = Checker::new(options.clone());
    c.register(&prelude.items, true);
    c.check_items(&prelude.items, true);
    c.prelude_diags = c.diags.len();
    c.register(&script.items, false);
    c.check_items(&script.items, false);
    c.finish(&script.items);
    c.out.program = c.build_program(prelude, script);
    c.out.globals = c
        .syms
        .iter()
        .filter(|g| !g.prelude)
        .map(|g| {
            let done = match &g.state {
                GState::Done(t) if !t.ty.is_error() => Some(t),
                _ => None,
            };
            GlobalInfo {
                name: g.name.clone(),
                kind: g.kind,
                span: g.span,
                ty: done.map(|t| t.ty.clone()),
                value: done.and_then(|t| t.num()),
            }
        })
        .collect();
    debug_assert_eq!(
        c.prelude_diags,
        0,
        "prelude has diagnostics: {:?}",
        &c.diags[..c.prelude_diags]
    );
    let mut diags = c.diags;
    diags.sort_by_key(|d| (d.span.start, d.span.end, d.code));
    diags.dedup();
    (c.out, diags)
}

/// The parsed prelude (built-in materials and helpers).
pub fn prelude_ast() -> &'static Script {
    static PRELUDE_AST: std::sync::OnceLock<Script> = std::sync::OnceLock::new();
    PRELUDE_AST.get_or_init(|| crate::front::parse(PRELUDE).expect("the prelude parses"))
}

/// Names with a fixed meaning inside expressions; declarations may not take them.
pub const RESERVED_NAMES: &[&str] = &[
    "t",
    "t_end",
    "dt",
    "x",
    "y",
    "z",
    "x0",
    "v",
    "I1bar",
    "I2bar",
    "J",
    "loss",
    "grad_norm",
    "iteration",
    "pi",
];

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SymKind {
    Mesh,
    Material,
    MaterialTemplate,
    Region,
    Chamber,
    Nodes,
    Elements,
    Obstacle,
    Param,
    Input,
    Let,
    Fn,
    Controller,
}

impl SymKind {
    /// The name a top-level item declares and its kind (`None` for sim, loss, optimize).
    pub fn of_item(item: &Item) -> Option<(&crate::front::ast::Ident, SymKind)> {
        use crate::front::ast::{DeclKind, ItemKind};
        Some(match &item.kind {
            ItemKind::Decl { kind, name, .. } => (
                name,
                match kind {
                    DeclKind::Mesh => SymKind::Mesh,
                    DeclKind::Region => SymKind::Region,
                    DeclKind::Chamber => SymKind::Chamber,
                    DeclKind::Nodes => SymKind::Nodes,
                    DeclKind::Elements => SymKind::Elements,
                    DeclKind::Obstacle => SymKind::Obstacle,
                },
            ),
            ItemKind::Material(m) if m.params.is_some() => (&m.name, SymKind::MaterialTemplate),
            ItemKind::Material(m) => (&m.name, SymKind::Material),
            ItemKind::Param(p) => (&p.name, SymKind::Param),
            ItemKind::Input(i) => (&i.name, SymKind::Input),
            ItemKind::Let(l) => (&l.name, SymKind::Let),
            ItemKind::Fn(f) if f.is_controller => (&f.name, SymKind::Controller),
            ItemKind::Fn(f) => (&f.name, SymKind::Fn),
            ItemKind::Sim(_) | ItemKind::Loss(_) | ItemKind::Optimize(_) => return None,
        })
    }

    fn with_article(self) -> String {
        expr::with_article(self.describe())
    }

    fn describe(self) -> &'static str {
        match self {
            SymKind::Mesh => "mesh",
            SymKind::Material => "material",
            SymKind::MaterialTemplate => "material template",
            SymKind::Region => "region",
            SymKind::Chamber => "chamber",
            SymKind::Nodes => "node set",
            SymKind::Elements => "element set",
            SymKind::Obstacle => "obstacle",
            SymKind::Param => "param",
            SymKind::Input => "input",
            SymKind::Let => "let binding",
            SymKind::Fn => "function",
            SymKind::Controller => "controller",
        }
    }
}

#[derive(Clone, Debug)]
enum GState {
    Unchecked,
    InProgress,
    Done(Typed),
}

#[derive(Clone, Debug)]
struct Global {
    name: String,
    kind: SymKind,
    span: Span,
    prelude: bool,
    used: bool,
    /// Index into the prelude's or the script's items.
    item: usize,
    state: GState,
}

/// A function-like signature: user `fn`/`controller` or a material template.
#[derive(Clone, Debug)]
struct Signature {
    params: Vec<SigParam>,
    ret: Ty,
    /// Variability of the body apart from its arguments (globals it reads, `t`, state).
    body_var: Var,
}

#[derive(Clone, Debug)]
struct SigParam {
    name: String,
    ty: Ty,
    has_default: bool,
}

#[derive(Clone, Debug)]
struct Local {
    typed: Typed,
    span: Span,
    used: bool,
    /// Warn when unused (sim/material lets); binders and parameters are exempt.
    warn_unused: bool,
    /// Its entry in the resolution table (`None` for implicit names and in the prelude).
    def: Option<usize>,
    /// A name the language binds here whose value comes from the run (`loss`, `grad_norm`,
    /// `iteration` in a stop condition), not a binding lowering inlines.
    implicit: bool,
}

/// Implicit names visible in the expression being checked.
#[derive(Clone, Copy, Debug, Default)]
struct Ctx {
    /// `t` (pressure, damping, controllers).
    time: bool,
    /// `x[n]`, `x0[n]`, `v[n]` (loss, controllers).
    state: bool,
    /// `x`, `y`, `z` as coordinates (inside `select`).
    coords: bool,
    /// The expression must not depend on params/inputs (geometry), reported by the caller.
    in_controller: bool,
    /// `force(OBSTACLE)` and `stretch(e)`: the loss and top-level lets, which the loss may
    /// read.
    loss_state: bool,
}

struct Checker {
    options: CheckOptions,
    diags: Vec<Diagnostic>,
    prelude_diags: usize,
    /// How deep constant calls are being folded (`fold_call`), to bound recursion.
    fold_depth: u32,
    /// Constant calls folded, by function and argument values: a call repeated with the same
    /// arguments is evaluated once (a function calling another twice doubles the work at
    /// every level otherwise: 24 such lines took minutes).
    folded: HashMap<(usize, Vec<u64>), expr::Folded>,
    /// Calls evaluated so far (at most `expr::MAX_FOLDS`), and whether that was exceeded
    /// inside the outermost call being folded.
    folds: usize,
    folds_exhausted: bool,
    globals: HashMap<String, usize>,
    syms: Vec<Global>,
    sigs: HashMap<usize, Signature>,
    scopes: Vec<HashMap<String, Local>>,
    ctx: Ctx,
    /// Items of the prelude and of the script, for on-demand checking.
    prelude_items: Vec<Item>,
    user_items: Vec<Item>,
    sim: items::SimInfo,
    loss_ty: Option<Ty>,
    optimized: Vec<String>,
    out: CheckedScript,
    /// The mesh, when a probe could read it.
    mesh: Option<mesh_probe::MeshSummary>,
    /// The shape of the region call checked last (picked up by its declaration).
    last_shape: Option<mesh_probe::Shape>,
    /// The surface of the `surface(…)` call checked last (picked up by its declaration).
    last_surface: Option<mesh_probe::SurfaceRef>,
    /// The selector of the selection call checked last (picked up by its declaration).
    last_selector: Option<mesh_probe::Selector>,
    /// Whether the code being checked is the prelude's (nothing of it enters the resolution
    /// table, whose spans point into the user's script).
    in_prelude: bool,
    /// Resolution-table entries by the declared name's span, and the user's globals' entries.
    def_at_span: HashMap<(usize, usize), usize>,
    global_defs: HashMap<usize, usize>,
    /// Uses recorded so far (a body checked twice, e.g. folded at a call, records once).
    seen_uses: std::collections::HashSet<(usize, usize)>,
    /// Each name's resolution and each expression's type, prelude and script alike, for the
    /// checked program ([`hir`]).
    hir: hir::Tables,
}

impl Checker {
    fn new(options: CheckOptions) -> Self {
        Checker {
            options,
            diags: Vec::new(),
            fold_depth: 0,
            folded: HashMap::new(),
            folds: 0,
            folds_exhausted: false,
            prelude_diags: 0,
            globals: HashMap::new(),
            syms: Vec::new(),
            sigs: HashMap::new(),
            scopes: Vec::new(),
            ctx: Ctx::default(),
            prelude_items: Vec::new(),
            user_items: Vec::new(),
            sim: items::SimInfo::default(),
            loss_ty: None,
            optimized: Vec::new(),
            out: CheckedScript::default(),
            mesh: None,
            last_surface: None,
            last_selector: None,
            last_shape: None,
            in_prelude: false,
            def_at_span: HashMap::new(),
            global_defs: HashMap::new(),
            seen_uses: std::collections::HashSet::new(),
            hir: hir::Tables::default(),
        }
    }

    /// The resolution-table entry of a declaration (one per declared name, however often its
    /// code is checked); `None` in the prelude.
    fn define(
        &mut self,
        name: &crate::front::ast::Ident,
        kind: DefKind,
        decl: Span,
        ty: Option<crate::front::ast::TypeExpr>,
    ) -> Option<usize> {
        if self.in_prelude {
            return None;
        }
        let key = (name.span.start, name.span.end);
        if let Some(&d) = self.def_at_span.get(&key) {
            return Some(d);
        }
        let r = &mut self.out.resolution;
        r.defs.push(Def {
            name: name.name.clone(),
            kind,
            span: name.span,
            decl,
            ty,
        });
        self.def_at_span.insert(key, r.defs.len() - 1);
        Some(r.defs.len() - 1)
    }

    /// Record that the name `id` (written in the user's script) resolved to entry `def`, or
    /// to nothing the script declares (`None`: a built-in, a prelude name, an implicit name, a
    /// mistake).
    fn record_use(&mut self, id: &crate::front::ast::Ident, def: Option<usize>) {
        if self.in_prelude || !self.seen_uses.insert((id.span.start, id.span.end)) {
            return;
        }
        match def {
            Some(d) => self.out.resolution.refs.push((id.span, d)),
            None => self.out.resolution.free.push(id.clone()),
        }
    }

    /// Record for the checked program what the name written at `id` refers to (the first
    /// check of a body decides: a body checked again resolves alike).
    fn resolve_name(&mut self, id: &crate::front::ast::Ident, to: hir::Name) {
        let key = (self.in_prelude, id.span.start, id.span.end);
        self.hir.names.entry(key).or_insert(to);
    }

    /// The resolution-table entry of a parameter of `owner` (a function, controller or
    /// material template).
    fn param_def(
        &mut self,
        owner: &crate::front::ast::Ident,
        p: &crate::front::ast::FnParam,
    ) -> Option<usize> {
        let end = p.default.as_ref().map_or(p.ty.span, |d| d.span);
        self.define(
            &p.name,
            DefKind::Param {
                owner: owner.name.clone(),
            },
            p.name.span.to(end),
            Some(p.ty.clone()),
        )
    }

    /// Record a use of the global `gid` (the user's declaration, or a prelude name).
    fn record_global_use(&mut self, id: &crate::front::ast::Ident, gid: usize) {
        let def = self.global_defs.get(&gid).copied();
        self.record_use(id, def);
    }

    fn err(&mut self, d: Diagnostic) {
        self.diags.push(d);
    }

    fn item(&self, prelude: bool, index: usize) -> Item {
        if prelude {
            self.prelude_items[index].clone()
        } else {
            self.user_items[index].clone()
        }
    }

    /// Look a name up in the local scopes, innermost first, marking it used; with the local's
    /// resolution-table entry.
    fn lookup_local_def(&mut self, name: &str) -> Option<(Typed, Option<usize>, bool)> {
        for scope in self.scopes.iter_mut().rev() {
            if let Some(l) = scope.get_mut(name) {
                l.used = true;
                return Some((l.typed.clone(), l.def, l.implicit));
            }
        }
        None
    }

    fn push_scope(&mut self) {
        self.scopes.push(HashMap::new());
    }

    fn pop_scope(&mut self) {
        if let Some(scope) = self.scopes.pop() {
            let mut unused: Vec<_> = scope
                .into_iter()
                .filter(|(n, l)| l.warn_unused && !l.used && !n.starts_with('_'))
                .collect();
            unused.sort_by_key(|(_, l)| l.span.start);
            for (name, l) in unused {
                self.err(
                    Diagnostic::warning(
                        "W0001",
                        l.span,
                        format!("the let binding `{name}` is declared but never used"),
                    )
                    .with_hint("remove it, or prefix the name with `_` to keep it"),
                );
            }
        }
    }

    fn declare_local(
        &mut self,
        name: &str,
        span: Span,
        typed: Typed,
        warn_unused: bool,
        def: Option<usize>,
    ) {
        if RESERVED_NAMES.contains(&name) {
            self.err(reserved_name(name, span));
        }
        let scope = self.scopes.last_mut().expect("a scope");
        if let Some(prev) = scope.get(name) {
            let prev_span = prev.span;
            self.err(
                Diagnostic::error("E0102", span, format!("`{name}` is declared twice"))
                    .with_note(prev_span, "first declared here"),
            );
            return;
        }
        scope.insert(
            name.to_string(),
            Local {
                typed,
                span,
                used: false,
                warn_unused,
                def,
                implicit: false,
            },
        );
    }

    /// All names visible now, for "did you mean".
    fn visible_names(&self) -> Vec<String> {
        let mut names: Vec<String> = self.globals.keys().cloned().collect();
        for s in &self.scopes {
            names.extend(s.keys().cloned());
        }
        names.extend(builtins::CONSTANTS.iter().map(|(n, _)| n.to_string()));
        names.extend(builtins::FUNCTIONS.iter().map(|n| n.to_string()));
        if self.ctx.time {
            names.push("t".into());
        }
        names.sort();
        names
    }

    fn unknown_name(&self, name: &str, span: Span) -> Diagnostic {
        let names = self.visible_names();
        let mut d = Diagnostic::error("E0101", span, format!("unknown name `{name}`"));
        if crate::sema::units::unit(name).is_some() {
            d = d.with_hint(format!(
                "`{name}` is a unit: write it right after a number without spaces inside the unit, e.g. `8 /{name}` or `1 {name}`"
            ));
        } else if let Some(s) = did_you_mean(name, names.iter().map(|s| s.as_str())) {
            d = d.with_hint(format!("did you mean `{s}`?"));
        }
        d
    }

    /// Type of a global, checking its declaration on first use.
    fn global_typed(&mut self, id: usize) -> Typed {
        self.global_typed_at(id, None)
    }

    /// Like [`Self::global_typed`], reporting a cycle at `use_span` (the reference).
    fn global_typed_at(&mut self, id: usize, use_span: Option<Span>) -> Typed {
        match self.syms[id].state.clone() {
            GState::Done(t) => t,
            GState::InProgress => {
                let g = &self.syms[id];
                let mesh_part = matches!(
                    g.kind,
                    SymKind::Nodes | SymKind::Elements | SymKind::Chamber | SymKind::Region
                );
                let mut d = Diagnostic::error(
                    "E0120",
                    use_span.unwrap_or(g.span),
                    format!("`{}` is used in its own definition", g.name),
                );
                if use_span.is_some() {
                    d = d.with_note(g.span, "declared here");
                }
                d = if mesh_part {
                    d.with_hint(format!(
                        "to name a part of the mesh, quote it: \"{}\"",
                        g.name
                    ))
                } else {
                    d.with_hint("break the cycle: a declaration cannot depend on its own value")
                };
                self.err(d);
                self.syms[id].state = GState::Done(Typed::error());
                Typed::error()
            }
            GState::Unchecked => {
                self.syms[id].state = GState::InProgress;
                let saved_scopes = std::mem::take(&mut self.scopes);
                let saved_ctx = std::mem::take(&mut self.ctx);
                let item = self.item(self.syms[id].prelude, self.syms[id].item);
                let saved_prelude = std::mem::replace(&mut self.in_prelude, self.syms[id].prelude);
                let t = self.check_decl(id, &item);
                self.in_prelude = saved_prelude;
                self.scopes = saved_scopes;
                self.ctx = saved_ctx;
                if matches!(self.syms[id].state, GState::InProgress) {
                    self.syms[id].state = GState::Done(t.clone());
                }
                match &self.syms[id].state {
                    GState::Done(t) => t.clone(),
                    _ => t,
                }
            }
        }
    }
}

fn reserved_name(name: &str, span: Span) -> Diagnostic {
    Diagnostic::error(
        "E0111",
        span,
        format!("`{name}` is a built-in name and cannot be declared"),
    )
    .with_hint(format!(
        "the reserved names are {}; choose another name",
        RESERVED_NAMES.join(", ")
    ))
}
