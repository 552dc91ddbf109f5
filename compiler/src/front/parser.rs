//! pest grammar → AST with spans, with the guards that keep any input cheap to diagnose:
//! invalid UTF-8, bracket nesting, expression depth and numbers out of range all become
//! diagnostics before they can overflow a stack or turn into infinities.

use super::ast::*;
use crate::diag::Diagnostic;
use pest::Parser as _;
use pest::iterators::{Pair, Pairs};
use std::num::NonZeroUsize;

#[derive(pest_derive::Parser)]
#[grammar = "front/soft.pest"]
struct SoftParser;

/// Deepest bracket nesting accepted. pest recurses per bracket; this keeps the stack small.
pub const MAX_BRACKET_DEPTH: usize = 64;
/// Deepest expression tree accepted (long operator chains fold into deep trees).
pub const MAX_EXPR_DEPTH: usize = 256;
/// Bound on pest rule calls, so no input can make the parser run for long.
const CALL_LIMIT: usize = 20_000_000;

type Result<T> = std::result::Result<T, Diagnostic>;

/// Decode bytes as UTF-8, or name the first invalid byte.
pub fn decode(bytes: &[u8]) -> std::result::Result<&str, Diagnostic> {
    std::str::from_utf8(bytes).map_err(|e| {
        let at = e.valid_up_to();
        // Report at the last valid position: the span must stay inside valid text.
        Diagnostic::error(
            "E0001",
            Span::new(at, at),
            format!(
                "the file is not valid UTF-8 (invalid byte 0x{:02x} at offset {at})",
                bytes[at]
            ),
        )
        .with_hint("save the script as UTF-8 text; .soft scripts are plain text")
    })
}

/// Parse a script. Returns the first syntax error; semantic checks come later.
pub fn parse(text: &str) -> Result<Script> {
    check_nesting(text)?;
    pest::set_call_limit(NonZeroUsize::new(CALL_LIMIT));
    let mut pairs = SoftParser::parse(Rule::file, text).map_err(|e| syntax_error(text, e))?;
    let file = pairs.next().expect("file rule");
    let mut items = Vec::new();
    for p in file.into_inner() {
        match p.as_rule() {
            Rule::EOI | Rule::semi => {}
            _ => items.push(build_item(p)?),
        }
    }
    Ok(Script { items })
}

/// Reject bracket nesting deeper than [`MAX_BRACKET_DEPTH`] before pest recurses into it.
fn check_nesting(text: &str) -> Result<()> {
    let bytes = text.as_bytes();
    let mut depth = 0usize;
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'#' => {
                while i < bytes.len() && bytes[i] != b'\n' {
                    i += 1;
                }
            }
            b'"' => {
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' && bytes[i] != b'\n' {
                    if bytes[i] == b'\\' {
                        i += 1;
                    }
                    i += 1;
                }
            }
            b'(' | b'[' | b'{' => {
                depth += 1;
                if depth > MAX_BRACKET_DEPTH {
                    return Err(Diagnostic::error(
                        "E0002",
                        Span::new(i, i + 1),
                        format!("brackets nested deeper than {MAX_BRACKET_DEPTH} levels"),
                    )
                    .with_hint("split the expression with `let` bindings"));
                }
            }
            b')' | b']' | b'}' => depth = depth.saturating_sub(1),
            _ => {}
        }
        i += 1;
    }
    Ok(())
}

fn syntax_error(text: &str, e: pest::error::Error<Rule>) -> Diagnostic {
    use pest::error::{ErrorVariant, InputLocation};
    let pos = match e.location {
        InputLocation::Pos(p) => p,
        InputLocation::Span((s, _)) => s,
    };
    let found = describe_found(text, pos);
    let (message, hint) = match &e.variant {
        ErrorVariant::ParsingError { positives, .. } => {
            let expected = describe_expected(positives);
            let hint = hint_for(text, pos, positives);
            if expected.is_empty() {
                (format!("unexpected {found}"), hint)
            } else {
                (format!("expected {expected}, found {found}"), hint)
            }
        }
        ErrorVariant::CustomError { message } => {
            if message.contains("call limit") {
                return Diagnostic::error(
                    "E0002",
                    Span::new(pos, pos),
                    "the script is too complex to parse",
                )
                .with_hint("split long expressions with `let` bindings");
            }
            (message.clone(), None)
        }
    };
    let end = (pos + found_len(text, pos)).min(text.len());
    let rest = &text[pos.min(text.len())..];
    let line = rest.split('\n').next().unwrap_or("");
    if line.starts_with('"') && !line[1..].contains('"') {
        return Diagnostic::error(
            "E0005",
            Span::new(pos, pos + 1),
            "this string is not closed",
        )
        .with_hint("strings must end with `\"` on the same line");
    }
    let mut d = Diagnostic::error("E0003", Span::new(pos, end), message);
    d.hint = hint;
    d
}

fn found_len(text: &str, pos: usize) -> usize {
    let rest = &text[pos.min(text.len())..];
    let Some(c) = rest.chars().next() else {
        return 0;
    };
    if c.is_alphanumeric() || c == '_' || c == '.' {
        rest.find(|c: char| !(c.is_alphanumeric() || c == '_' || c == '.'))
            .unwrap_or(rest.len())
            .max(c.len_utf8())
    } else {
        c.len_utf8()
    }
}

fn describe_found(text: &str, pos: usize) -> String {
    let rest = &text[pos.min(text.len())..];
    match rest.chars().next() {
        None => "end of file".into(),
        Some('\n') | Some('\r') => "end of line".into(),
        Some(c) if c.is_control() => format!("the control character U+{:04X}", c as u32),
        Some(_) => {
            let tok: String = rest[..found_len(text, pos)].chars().take(40).collect();
            if is_keyword(&tok) {
                format!("keyword `{tok}`")
            } else {
                format!("`{tok}`")
            }
        }
    }
}

pub const KEYWORDS: &[&str] = &[
    "and",
    "at",
    "chamber",
    "controller",
    "elements",
    "else",
    "end",
    "every",
    "false",
    "fix",
    "fn",
    "for",
    "from",
    "if",
    "in",
    "input",
    "iterations",
    "let",
    "material",
    "mesh",
    "nodes",
    "not",
    "optimize",
    "or",
    "output",
    "over",
    "param",
    "region",
    "sim",
    "steps",
    "stop",
    "then",
    "true",
    "use",
    "validate",
    "when",
    "with",
];

pub fn is_keyword(s: &str) -> bool {
    KEYWORDS.contains(&s)
}

fn rule_description(r: Rule) -> Option<&'static str> {
    use Rule::*;
    Some(match r {
        ident | arg_name => "a name",
        setting_name => "a statement",
        expr | if_expr | or_expr | and_expr | not_expr | cmp_expr | range_expr | add_expr
        | mul_expr | unary_expr | pow_expr | postfix_expr | quantity | array | string
        | bool_lit | paren | reduction | reduce_op | not_op | neg_op | number | array_body
        | kw_true | kw_false | kw_if | kw_not => "an expression",
        EOI => "end of file",
        mesh_decl | material_decl | region_decl | chamber_decl | nodes_decl | elements_decl
        | obstacle_decl | kw_obstacle | param_decl | input_decl | fn_decl | controller_decl
        | sim_block | loss_decl | optimize_decl | kw_mesh | kw_material | kw_region
        | kw_chamber | kw_nodes | kw_elements | kw_param | kw_input | kw_fn | kw_controller
        | kw_sim | kw_loss | kw_optimize => "a declaration",
        let_decl | kw_let => "`let`",
        fix_stmt | kw_fix | pressure_stmt | kw_pressure | use_stmt | kw_use | output_stmt
        | kw_output | contact_stmt | kw_contact | assign => "a statement",
        stop_stmt | kw_stop | validate_stmt | kw_validate => "a statement",
        energy_def => "`W(I1bar, I2bar, J) = …`",
        add_op | mul_op | cmp_op | pow_op | range_op | kw_and | kw_or => "an operator",
        call_args | index | field => "an operator",
        unit | unit_atom | unit_name | unit_div | unit_mul => "a unit",
        unit_exp | int_lit => "an integer",
        type_expr | dim_expr | dim_factor | dim_one => "a type such as `pressure` or `length[3]`",
        shape | shape_item | any_len => "a shape",
        dim_op => "`*` or `/`",
        eq => "`=`",
        lbrace => "`{`",
        rbrace => "`}`",
        lparen => "`(`",
        rparen => "`)`",
        lbracket => "`[`",
        rbracket => "`]`",
        comma => "`,`",
        colon => "`:`",
        arrow => "`->`",
        semi => "`;`",
        bounds | kw_in => "`in`",
        open_bound => "`..`",
        kw_from => "`from`",
        kw_with => "`with`",
        kw_for | iterations => "`for`",
        kw_iterations => "`iterations`",
        kw_every => "`every`",
        kw_steps | steps_word => "`steps`",
        kw_when => "`when`",
        kw_then => "`then`",
        kw_else => "`else`",
        kw_at | at_end => "`at`",
        kw_end => "`end`",
        kw_over | over_range | loss_when => "`at end` or `over [t0, t1]`",
        fn_params | fn_param => "a parameter list",
        ret_type => "`->`",
        material_body => "`{`",
        optimize_body => "`{`",
        bound => "a bound",
        arg => "an argument",
        _ => return None,
    })
}

fn describe_expected(positives: &[Rule]) -> String {
    let mut seen: Vec<&str> = Vec::new();
    for r in positives {
        if let Some(d) = rule_description(*r)
            && !seen.contains(&d)
        {
            seen.push(d);
        }
    }
    // Operators, postfixes and `;` are always possible after a complete expression or
    // statement; listing them only adds noise.
    if seen.len() > 1 {
        let noise = ["an operator", "a unit", "`(`", "`[`", "`;`"];
        seen.retain(|d| !noise.contains(d));
    }
    if seen.contains(&"a statement") || seen.contains(&"a declaration") {
        seen.retain(|d| *d != "`let`");
    }
    match seen.len() {
        0 => String::new(),
        1 => seen[0].to_string(),
        n => format!("{} or {}", seen[..n - 1].join(", "), seen[n - 1]),
    }
}

fn hint_for(text: &str, pos: usize, positives: &[Rule]) -> Option<String> {
    let rest = &text[pos.min(text.len())..];
    let word: String = rest
        .chars()
        .take_while(|c| c.is_alphanumeric() || *c == '_')
        .collect();
    if is_keyword(&word) && positives.contains(&Rule::ident) {
        return Some(format!("`{word}` is a keyword; choose another name"));
    }
    if rest.starts_with("//")
        || rest.starts_with("/*")
        || (rest.starts_with(['/', '*']) && text[..pos].ends_with('/'))
    {
        return Some("comments start with `#`".into());
    }
    if rest.starts_with('"') {
        return Some("strings must end with `\"` on the same line".into());
    }
    if rest.starts_with('\'') {
        return Some("strings use double quotes: \"…\"".into());
    }
    if rest.starts_with("**") || (rest.starts_with('*') && text[..pos].ends_with('*')) {
        return Some("powers are written with `^`, e.g. `x^2`".into());
    }
    if positives.contains(&Rule::eq) && rest.starts_with(':') {
        return Some("declarations use `=`; `:` introduces a type or a named argument".into());
    }
    None
}

// ---------------------------------------------------------------- AST building

/// The span of a pair without trailing whitespace and comments, which pest includes when a
/// rule ends in a repetition (`a ~ b*`).
fn span(p: &Pair<Rule>) -> Span {
    let s = p.as_span();
    let text = s.get_input();
    Span::new(s.start(), trim_trivia_end(text, s.start(), s.end()))
}

fn trim_trivia_end(text: &str, start: usize, mut end: usize) -> usize {
    let bytes = text.as_bytes();
    // Trivia that pest swallowed ends in whitespace (the newline after a comment), except at
    // the end of the file; anything else ends in a token.
    if end > start && end < text.len() && !bytes[end - 1].is_ascii_whitespace() {
        return end;
    }
    loop {
        while end > start && bytes[end - 1].is_ascii_whitespace() {
            end -= 1;
        }
        let line_start = text[start..end]
            .rfind('\n')
            .map_or(start, |i| start + i + 1);
        let line = &text[line_start..end];
        if !line.contains('#') {
            return end;
        }
        match comment_start(line) {
            Some(h) => end = line_start + h,
            None => return end,
        }
    }
}

/// Byte index of the first `#` outside a string in one line of code.
fn comment_start(line: &str) -> Option<usize> {
    let mut in_string = false;
    let mut escaped = false;
    for (i, b) in line.bytes().enumerate() {
        match b {
            _ if escaped => escaped = false,
            b'\\' if in_string => escaped = true,
            b'"' => in_string = !in_string,
            b'#' if !in_string => return Some(i),
            _ => {}
        }
    }
    None
}

/// Inner pairs without punctuation and keywords: only the parts that carry content.
fn content(p: Pair<Rule>) -> impl Iterator<Item = Pair<Rule>> {
    p.into_inner().filter(|q| !is_punct(q.as_rule()))
}

fn is_punct(r: Rule) -> bool {
    use Rule::*;
    matches!(
        r,
        eq | lbrace
            | rbrace
            | lparen
            | rparen
            | lbracket
            | rbracket
            | comma
            | colon
            | arrow
            | semi
            | kw_mesh
            | kw_region
            | kw_chamber
            | kw_nodes
            | kw_elements
            | kw_material
            | kw_param
            | kw_input
            | kw_let
            | kw_fn
            | kw_controller
            | kw_sim
            | kw_loss
            | kw_optimize
            | kw_in
            | kw_from
            | kw_with
            | kw_for
            | kw_iterations
            | kw_fix
            | kw_pressure
            | kw_obstacle
            | kw_contact
            | kw_use
            | kw_output
            | kw_every
            | kw_stop
            | kw_when
            | kw_validate
            | kw_at
            | kw_end
            | kw_over
            | kw_if
            | kw_then
            | kw_else
    )
}

fn ident(p: Pair<Rule>) -> Ident {
    Ident {
        name: p.as_str().to_string(),
        span: span(&p),
    }
}

fn build_item(p: Pair<Rule>) -> Result<Item> {
    let sp = span(&p);
    let rule = p.as_rule();
    let kind = match rule {
        Rule::mesh_decl
        | Rule::region_decl
        | Rule::chamber_decl
        | Rule::nodes_decl
        | Rule::elements_decl
        | Rule::obstacle_decl => {
            let kind = match rule {
                Rule::mesh_decl => DeclKind::Mesh,
                Rule::region_decl => DeclKind::Region,
                Rule::chamber_decl => DeclKind::Chamber,
                Rule::nodes_decl => DeclKind::Nodes,
                Rule::obstacle_decl => DeclKind::Obstacle,
                _ => DeclKind::Elements,
            };
            let mut it = content(p);
            let name = ident(it.next().unwrap());
            let value = build_expr(it.next().unwrap())?;
            ItemKind::Decl { kind, name, value }
        }
        Rule::material_decl => {
            let mut name = None;
            let mut params = None;
            let mut body = None;
            for q in content(p) {
                match q.as_rule() {
                    Rule::ident => name = Some(ident(q)),
                    Rule::fn_params => params = Some(build_fn_params(q)?),
                    Rule::expr => body = Some(MaterialBody::Expr(build_expr(q)?)),
                    Rule::material_body => {
                        let mut stmts = Vec::new();
                        for s in content(q) {
                            stmts.push(build_stmt(s)?);
                        }
                        body = Some(MaterialBody::Block(stmts));
                    }
                    _ => {}
                }
            }
            ItemKind::Material(MaterialDecl {
                name: name.unwrap(),
                params,
                body: body.unwrap(),
            })
        }
        Rule::param_decl => {
            let mut it = content(p);
            let name = ident(it.next().unwrap());
            let ty = build_type(it.next().unwrap())?;
            let init = build_expr(it.next().unwrap())?;
            let bounds = match it.next() {
                Some(b) => Some(build_bounds(b)?),
                None => None,
            };
            ItemKind::Param(ParamDecl {
                name,
                ty,
                init,
                bounds,
            })
        }
        Rule::input_decl => {
            let mut it = content(p);
            let name = ident(it.next().unwrap());
            let ty = build_type(it.next().unwrap())?;
            let source = build_expr(it.next().unwrap())?;
            ItemKind::Input(InputDecl { name, ty, source })
        }
        Rule::let_decl => ItemKind::Let(build_let(p)?),
        Rule::fn_decl | Rule::controller_decl => {
            let is_controller = rule == Rule::controller_decl;
            let mut it = content(p);
            let name = ident(it.next().unwrap());
            let params = build_fn_params(it.next().unwrap())?;
            let mut ret = None;
            let mut body = None;
            for q in it {
                match q.as_rule() {
                    Rule::ret_type => {
                        ret = Some(build_type(content(q).next().unwrap())?);
                    }
                    _ => body = Some(build_expr(q)?),
                }
            }
            ItemKind::Fn(FnDecl {
                is_controller,
                name,
                params,
                ret,
                body: body.unwrap(),
            })
        }
        Rule::sim_block => {
            let mut stmts = Vec::new();
            for s in content(p) {
                stmts.push(build_stmt(s)?);
            }
            ItemKind::Sim(stmts)
        }
        Rule::loss_decl => {
            let mut it = content(p);
            let value = build_expr(it.next().unwrap())?;
            let when = match it.next() {
                None => LossWhen::Default,
                Some(w) => {
                    let inner = content(w).next().unwrap();
                    match inner.as_rule() {
                        Rule::at_end => LossWhen::AtEnd(span(&inner)),
                        _ => {
                            let sp = span(&inner);
                            let mut r = content(inner);
                            let from = build_expr(r.next().unwrap())?;
                            let to = build_expr(r.next().unwrap())?;
                            LossWhen::Over { from, to, span: sp }
                        }
                    }
                }
            };
            ItemKind::Loss(LossDecl { value, when })
        }
        Rule::optimize_decl => {
            let mut targets = Vec::new();
            let mut optimizer = None;
            let mut iterations = None;
            let mut body = None;
            for q in content(p) {
                match q.as_rule() {
                    Rule::ident => targets.push(ident(q)),
                    Rule::expr => optimizer = Some(build_expr(q)?),
                    Rule::iterations => {
                        iterations = Some(build_expr(content(q).next().unwrap())?);
                    }
                    Rule::optimize_body => {
                        let mut stmts = Vec::new();
                        for s in content(q) {
                            stmts.push(build_stmt(s)?);
                        }
                        body = Some(stmts);
                    }
                    _ => {}
                }
            }
            ItemKind::Optimize(OptimizeDecl {
                targets,
                optimizer: optimizer.unwrap(),
                iterations,
                body,
            })
        }
        r => unreachable!("unexpected item rule {r:?}"),
    };
    Ok(Item { kind, span: sp })
}

fn build_let(p: Pair<Rule>) -> Result<LetDecl> {
    let mut it = content(p);
    let name = ident(it.next().unwrap());
    let mut ty = None;
    let mut value = None;
    for q in it {
        match q.as_rule() {
            Rule::type_expr => ty = Some(build_type(q)?),
            _ => value = Some(build_expr(q)?),
        }
    }
    Ok(LetDecl {
        name,
        ty,
        value: value.unwrap(),
    })
}

fn build_fn_params(p: Pair<Rule>) -> Result<Vec<FnParam>> {
    let mut out = Vec::new();
    for q in content(p) {
        let mut it = content(q);
        let name = ident(it.next().unwrap());
        let ty = build_type(it.next().unwrap())?;
        let default = match it.next() {
            Some(e) => Some(build_expr(e)?),
            None => None,
        };
        out.push(FnParam { name, ty, default });
    }
    Ok(out)
}

fn build_bounds(p: Pair<Rule>) -> Result<Bounds> {
    let sp = span(&p);
    let mut ends = Vec::new();
    for b in content(p) {
        let inner = content(b).next().unwrap();
        ends.push(match inner.as_rule() {
            Rule::open_bound => None,
            _ => Some(build_expr(inner)?),
        });
    }
    let upper = ends.pop().unwrap();
    let lower = ends.pop().unwrap();
    Ok(Bounds {
        lower,
        upper,
        span: sp,
    })
}

fn build_type(p: Pair<Rule>) -> Result<TypeExpr> {
    let sp = span(&p);
    let mut it = content(p);
    let dim = build_dim(it.next().unwrap());
    let mut shape = Vec::new();
    if let Some(s) = it.next() {
        for item in content(s) {
            let inner = content(item).next().unwrap();
            shape.push(match inner.as_rule() {
                Rule::any_len => ShapeItem::Any(span(&inner)),
                Rule::int_lit => ShapeItem::Len(inner.as_str().to_string(), span(&inner)),
                _ => ShapeItem::Set(ident(inner)),
            });
        }
    }
    Ok(TypeExpr {
        dim,
        shape,
        span: sp,
    })
}

fn build_dim(p: Pair<Rule>) -> DimExpr {
    let sp = span(&p);
    let mut first = None;
    let mut rest = Vec::new();
    let mut op = DimOp::Mul;
    for q in content(p) {
        match q.as_rule() {
            Rule::dim_op => {
                op = if q.as_str() == "/" {
                    DimOp::Div
                } else {
                    DimOp::Mul
                }
            }
            _ => {
                let f = build_dim_factor(q);
                if first.is_none() {
                    first = Some(f);
                } else {
                    rest.push((op, f));
                }
            }
        }
    }
    DimExpr {
        first: first.unwrap(),
        rest,
        span: sp,
    }
}

fn build_dim_factor(p: Pair<Rule>) -> DimFactor {
    let sp = span(&p);
    let mut base = None;
    let mut power = None;
    for q in content(p) {
        match q.as_rule() {
            Rule::dim_one => base = Some(DimBase::One),
            Rule::ident => base = Some(DimBase::Named(ident(q))),
            Rule::dim_expr => base = Some(DimBase::Group(Box::new(build_dim(q)))),
            Rule::int_lit => power = Some((q.as_str().to_string(), span(&q))),
            _ => {}
        }
    }
    DimFactor {
        base: base.unwrap(),
        power,
        span: sp,
    }
}

fn build_stmt(p: Pair<Rule>) -> Result<Stmt> {
    let sp = span(&p);
    let rule = p.as_rule();
    let kind = match rule {
        Rule::let_decl => StmtKind::Let(build_let(p)?),
        Rule::assign => {
            let mut it = content(p);
            let name = ident(it.next().unwrap());
            let value = build_expr(it.next().unwrap())?;
            StmtKind::Assign { name, value }
        }
        Rule::energy_def => {
            let mut names = Vec::new();
            let mut body = None;
            for q in content(p) {
                match q.as_rule() {
                    Rule::ident => names.push(ident(q)),
                    _ => body = Some(build_expr(q)?),
                }
            }
            let name = names.remove(0);
            StmtKind::Energy {
                name,
                args: names,
                body: body.unwrap(),
            }
        }
        Rule::fix_stmt => StmtKind::Fix(content(p).map(ident).collect()),
        Rule::pressure_stmt => {
            let mut it = content(p);
            let chamber = ident(it.next().unwrap());
            let value = build_expr(it.next().unwrap())?;
            StmtKind::Pressure { chamber, value }
        }
        Rule::use_stmt => {
            let mut it = content(p);
            let material = ident(it.next().unwrap());
            let set = it.next().map(ident);
            StmtKind::Use { material, set }
        }
        Rule::contact_stmt => {
            let mut it = content(p);
            let body = ident(it.next().unwrap());
            let obstacle = ident(it.next().unwrap());
            let args = match it.next() {
                Some(q) => call_args(q)?.0,
                None => Vec::new(),
            };
            StmtKind::Contact {
                body,
                obstacle,
                args,
            }
        }
        Rule::output_stmt => {
            let mut it = content(p);
            let what = build_expr(it.next().unwrap())?;
            let every = build_expr(it.next().unwrap())?;
            let steps = it.next().is_some();
            StmtKind::Output { what, every, steps }
        }
        Rule::stop_stmt => StmtKind::Stop(build_expr(content(p).next().unwrap())?),
        Rule::validate_stmt => {
            let mut it = content(p);
            let input = ident(it.next().unwrap());
            let source = build_expr(it.next().unwrap())?;
            StmtKind::Validate { input, source }
        }
        r => unreachable!("unexpected statement rule {r:?}"),
    };
    Ok(Stmt { kind, span: sp })
}

// ---------------------------------------------------------------- expressions

/// An expression with its tree depth, so chains can be refused before they grow unbounded.
type Built = (Expr, usize);

/// A call's arguments and their deepest tree depth.
fn call_args(q: Pair<Rule>) -> Result<(Vec<Arg>, usize)> {
    let mut args = Vec::new();
    let mut d = 0;
    for a in content(q) {
        let mut name = None;
        let mut value = None;
        for part in content(a) {
            match part.as_rule() {
                Rule::arg_name => name = Some(ident(part)),
                _ => value = Some(expr(part)?),
            }
        }
        let v = value.unwrap();
        d = d.max(v.1);
        args.push(Arg { name, value: v.0 });
    }
    Ok((args, d))
}

fn build_expr(p: Pair<Rule>) -> Result<Expr> {
    Ok(expr(p)?.0)
}

fn too_deep(sp: Span) -> Diagnostic {
    Diagnostic::error(
        "E0002",
        sp,
        format!("expression nested deeper than {MAX_EXPR_DEPTH} levels"),
    )
    .with_hint("split the expression with `let` bindings")
}

fn node(kind: ExprKind, sp: Span, depth: usize) -> Result<Built> {
    if depth > MAX_EXPR_DEPTH {
        return Err(too_deep(sp));
    }
    Ok((Expr { kind, span: sp }, depth))
}

fn binary(op: BinOp, l: Built, r: Built) -> Result<Built> {
    let sp = l.0.span.to(r.0.span);
    let d = l.1.max(r.1) + 1;
    node(
        ExprKind::Binary {
            op,
            lhs: Box::new(l.0),
            rhs: Box::new(r.0),
        },
        sp,
        d,
    )
}

fn unary(op: UnaryOp, op_span: Span, e: Built) -> Result<Built> {
    let sp = op_span.to(e.0.span);
    let d = e.1 + 1;
    node(
        ExprKind::Unary {
            op,
            operand: Box::new(e.0),
        },
        sp,
        d,
    )
}

fn bin_op(s: &str) -> BinOp {
    match s {
        "or" => BinOp::Or,
        "and" => BinOp::And,
        "==" => BinOp::Eq,
        "!=" => BinOp::Ne,
        "<" => BinOp::Lt,
        "<=" => BinOp::Le,
        ">" => BinOp::Gt,
        ">=" => BinOp::Ge,
        ".." => BinOp::Range,
        "+" => BinOp::Add,
        "-" => BinOp::Sub,
        "*" => BinOp::Mul,
        "/" => BinOp::Div,
        "@" => BinOp::MatMul,
        _ => BinOp::Pow,
    }
}

/// Left fold of `operand (op operand)*`.
fn fold_left(pairs: Pairs<Rule>) -> Result<Built> {
    let mut acc: Option<Built> = None;
    let mut op = None;
    for q in pairs {
        match q.as_rule() {
            Rule::add_op
            | Rule::mul_op
            | Rule::cmp_op
            | Rule::range_op
            | Rule::kw_and
            | Rule::kw_or => op = Some(bin_op(q.as_str())),
            _ => {
                let rhs = expr(q)?;
                acc = Some(match (acc, op.take()) {
                    (Some(l), Some(o)) => binary(o, l, rhs)?,
                    _ => rhs,
                });
            }
        }
    }
    Ok(acc.unwrap())
}

fn expr(p: Pair<Rule>) -> Result<Built> {
    let sp = span(&p);
    match p.as_rule() {
        Rule::expr => expr(p.into_inner().next().unwrap()),
        Rule::if_expr => {
            let mut it = content(p);
            let c = expr(it.next().unwrap())?;
            let t = expr(it.next().unwrap())?;
            let o = expr(it.next().unwrap())?;
            let d = c.1.max(t.1).max(o.1) + 1;
            node(
                ExprKind::If {
                    cond: Box::new(c.0),
                    then: Box::new(t.0),
                    otherwise: Box::new(o.0),
                },
                sp,
                d,
            )
        }
        Rule::or_expr
        | Rule::and_expr
        | Rule::cmp_expr
        | Rule::range_expr
        | Rule::add_expr
        | Rule::mul_expr => fold_left(p.into_inner()),
        Rule::not_expr | Rule::unary_expr => {
            let mut ops = Vec::new();
            let mut operand = None;
            for q in p.into_inner() {
                match q.as_rule() {
                    Rule::not_op => ops.push((UnaryOp::Not, span(&q))),
                    Rule::neg_op => ops.push((UnaryOp::Neg, span(&q))),
                    _ => operand = Some(expr(q)?),
                }
            }
            let mut acc = operand.unwrap();
            for (op, s) in ops.into_iter().rev() {
                acc = unary(op, s, acc)?;
            }
            Ok(acc)
        }
        Rule::pow_expr => {
            // base (^ -* operand)*, right-associative.
            let mut operands: Vec<(Vec<Span>, Built)> = Vec::new();
            let mut negs = Vec::new();
            for q in p.into_inner() {
                match q.as_rule() {
                    Rule::pow_op => {}
                    Rule::neg_op => negs.push(span(&q)),
                    _ => operands.push((std::mem::take(&mut negs), expr(q)?)),
                }
            }
            let (mut negs_last, mut acc) = operands.pop().unwrap();
            while let Some((negs_prev, base)) = operands.pop() {
                for s in negs_last.into_iter().rev() {
                    acc = unary(UnaryOp::Neg, s, acc)?;
                }
                acc = binary(BinOp::Pow, base, acc)?;
                negs_last = negs_prev;
            }
            Ok(acc)
        }
        Rule::postfix_expr => {
            let mut it = p.into_inner();
            let mut acc = expr(it.next().unwrap())?;
            for q in it {
                let qs = span(&q);
                let whole = acc.0.span.to(qs);
                acc = match q.as_rule() {
                    Rule::call_args => {
                        let (args, depth) = call_args(q)?;
                        let d = acc.1.max(depth);
                        node(
                            ExprKind::Call {
                                callee: Box::new(acc.0),
                                args,
                            },
                            whole,
                            d + 1,
                        )?
                    }
                    Rule::index => {
                        let mut indices = Vec::new();
                        let mut d = acc.1;
                        for i in content(q) {
                            let b = expr(i)?;
                            d = d.max(b.1);
                            indices.push(b.0);
                        }
                        node(
                            ExprKind::Index {
                                base: Box::new(acc.0),
                                indices,
                            },
                            whole,
                            d + 1,
                        )?
                    }
                    _ => {
                        let field = ident(content(q).next().unwrap());
                        let d = acc.1 + 1;
                        node(
                            ExprKind::Field {
                                base: Box::new(acc.0),
                                field,
                            },
                            whole,
                            d,
                        )?
                    }
                };
            }
            Ok(acc)
        }
        Rule::paren => {
            let inner = expr(content(p).next().unwrap())?;
            let d = inner.1 + 1;
            node(ExprKind::Paren(Box::new(inner.0)), sp, d)
        }
        Rule::reduction => {
            let mut it = content(p);
            let op = match it.next().unwrap().as_str() {
                "sum" => ReduceOp::Sum,
                "mean" => ReduceOp::Mean,
                "area_mean" => ReduceOp::AreaMean,
                "max" => ReduceOp::Max,
                _ => ReduceOp::Min,
            };
            let var = ident(it.next().unwrap());
            let domain = expr(it.next().unwrap())?;
            let body = expr(it.next().unwrap())?;
            let d = domain.1.max(body.1) + 1;
            node(
                ExprKind::Reduce {
                    op,
                    var,
                    domain: Box::new(domain.0),
                    body: Box::new(body.0),
                },
                sp,
                d,
            )
        }
        Rule::quantity => {
            let mut it = p.into_inner();
            let num = it.next().unwrap();
            let text = num.as_str().to_string();
            let value = parse_number(&text, span(&num))?;
            let is_int = text.bytes().all(|b| b.is_ascii_digit());
            let unit = match it.next() {
                Some(u) => Some(build_unit(u)?),
                None => None,
            };
            node(
                ExprKind::Number {
                    text,
                    value,
                    is_int,
                    unit,
                },
                sp,
                1,
            )
        }
        Rule::array => {
            let mut it = p.into_inner();
            let body = it.next().unwrap();
            let mut items = Vec::new();
            let mut d = 0;
            for e in content(body) {
                let b = expr(e)?;
                d = d.max(b.1);
                items.push(b.0);
            }
            let unit = match it.next() {
                Some(u) => Some(build_unit(u)?),
                None => None,
            };
            node(ExprKind::Array { items, unit }, sp, d + 1)
        }
        Rule::string => {
            let inner = p.into_inner().next().unwrap();
            let s = unescape(inner.as_str(), span(&inner).start)?;
            node(ExprKind::Str(s), sp, 1)
        }
        Rule::bool_lit => node(ExprKind::Bool(p.as_str().trim() == "true"), sp, 1),
        Rule::ident => node(ExprKind::Name(ident(p)), sp, 1),
        r => unreachable!("unexpected expression rule {r:?}"),
    }
}

fn parse_number(text: &str, sp: Span) -> Result<f64> {
    let mantissa = text.split(['e', 'E']).next().unwrap_or("");
    let nonzero = mantissa.bytes().any(|b| (b'1'..=b'9').contains(&b));
    match text.parse::<f64>() {
        Ok(v) if v == 0.0 && nonzero => Err(Diagnostic::error(
            "E0004",
            sp,
            format!(
                "the number `{}` is too small: it rounds to 0",
                truncate(text, 40)
            ),
        )
        .with_hint("numbers must be 0 or larger in magnitude than about 4.9e-324")),
        Ok(v) if v.is_finite() => Ok(v),
        _ => Err(Diagnostic::error(
            "E0004",
            sp,
            format!("the number `{}` is out of range", truncate(text, 40)),
        )
        .with_hint("numbers must be finite 64-bit floats (magnitude below about 1.8e308)")),
    }
}

fn truncate(s: &str, n: usize) -> String {
    if s.chars().count() > n {
        format!("{}…", s.chars().take(n).collect::<String>())
    } else {
        s.to_string()
    }
}

fn build_unit(p: Pair<Rule>) -> Result<Unit> {
    let sp = span(&p);
    let mut factors = Vec::new();
    let mut divides = false;
    for q in p.into_inner() {
        match q.as_rule() {
            Rule::unit_div => divides = true,
            Rule::unit_mul => divides = false,
            Rule::unit_atom => {
                let fsp = span(&q);
                let mut it = q.into_inner();
                let name = it.next().unwrap().as_str().to_string();
                let written_power = match it.next() {
                    Some(e) => Some(
                        e.as_str()
                            .parse::<i32>()
                            .ok()
                            .filter(|p| p.abs() <= 12)
                            .ok_or_else(|| {
                                Diagnostic::error(
                                    "E0004",
                                    fsp,
                                    format!(
                                        "the unit power `{}` is out of range",
                                        truncate(e.as_str(), 20)
                                    ),
                                )
                                .with_hint("unit powers must lie between -12 and 12")
                            })?,
                    ),
                    None => None,
                };
                let p = written_power.unwrap_or(1);
                factors.push(UnitFactor {
                    name,
                    power: if divides { -p } else { p },
                    written_power,
                    divides,
                    span: fsp,
                });
            }
            _ => {}
        }
    }
    Ok(Unit { factors, span: sp })
}

fn unescape(raw: &str, start: usize) -> Result<String> {
    let mut out = String::with_capacity(raw.len());
    let mut chars = raw.char_indices();
    while let Some((i, c)) = chars.next() {
        if c != '\\' {
            out.push(c);
            continue;
        }
        match chars.next() {
            Some((_, 'n')) => out.push('\n'),
            Some((_, 't')) => out.push('\t'),
            Some((_, '\\')) => out.push('\\'),
            Some((_, '"')) => out.push('"'),
            Some((j, other)) => {
                return Err(Diagnostic::error(
                    "E0005",
                    Span::new(start + i, start + j + other.len_utf8()),
                    format!("unknown escape `\\{other}` in string"),
                )
                .with_hint("the escapes are \\n, \\t, \\\\ and \\\"; use / in paths"));
            }
            None => out.push('\\'),
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prelude_and_examples_parse() {
        let prelude = include_str!("../sema/prelude.soft");
        parse(prelude).unwrap();
        for (path, text) in crate::example_scripts() {
            let checked = crate::check_source(&text, &Default::default());
            let file = crate::diag::SourceFile::new("x", &text);
            for d in &checked.diagnostics {
                eprintln!("{}: {}", path.display(), file.render(d));
            }
            assert!(checked.diagnostics.is_empty());
        }
    }
}
