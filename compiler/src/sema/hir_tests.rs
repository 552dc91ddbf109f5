//! The checked program: names resolved as the checker resolved them, types attached, numbers
//! in SI.

use super::*;
use crate::sema::units::Dim;

fn program(text: &str) -> Program {
    let ast = crate::front::parse(text).unwrap();
    let (checked, diags) = crate::sema::check(&ast, &Default::default());
    // Fragments: no mesh (E0310), no sim block (E0311), nothing else wrong.
    let wrong: Vec<_> = (diags.iter())
        .filter(|d| d.is_error() && !["E0310", "E0311"].contains(&d.code))
        .collect();
    assert!(wrong.is_empty(), "{wrong:?}");
    checked.program
}

fn user<'p>(p: &'p Program, name: &str) -> &'p Decl {
    let (_, d) = p.find(name).unwrap();
    assert!(!d.prelude, "{name}");
    d
}

/// Every expression of the checked program, depth first.
fn walk<'e>(e: &'e Expr, out: &mut Vec<&'e Expr>) {
    out.push(e);
    e.for_each_child(|c| walk(c, out));
}

#[test]
fn names_resolve_as_the_checker_resolved_them() {
    let p = program(
        "param k: 1/length = 2 /mm\n\
         fn f(k: length) -> length = k * 2\n\
         let g = f(3 mm) * k\n\
         let h = sum(i in 0..3) i * lame_lambda(1 kPa, 0.3)\n",
    );
    // A parameter shadows the global of its name; outside, the global.
    let DeclKind::Fn(f) = &user(&p, "f").kind else {
        panic!()
    };
    let ExprKind::Binary { lhs, .. } = &f.body.kind else {
        panic!("{:?}", f.body)
    };
    assert_eq!(lhs.kind, ExprKind::Name(Name::Local("k".into())));
    let DeclKind::Let(g) = &user(&p, "g").kind else {
        panic!()
    };
    let (k, _) = p.find("k").unwrap();
    let (fid, _) = p.find("f").unwrap();
    let ExprKind::Binary { lhs, rhs, .. } = &g.kind else {
        panic!()
    };
    assert!(matches!(&lhs.kind, ExprKind::Call { callee: Callee::Decl(id), .. } if *id == fid));
    assert_eq!(rhs.kind, ExprKind::Name(Name::Global(k)));
    // A reduction's variable is local; a prelude function is a declaration of the prelude;
    // a built-in function is built in.
    let DeclKind::Let(h) = &user(&p, "h").kind else {
        panic!()
    };
    let mut all = Vec::new();
    walk(h, &mut all);
    assert!(
        all.iter()
            .any(|e| e.kind == ExprKind::Name(Name::Local("i".into())))
    );
    let lame = all
        .iter()
        .find_map(|e| match &e.kind {
            ExprKind::Call {
                callee: Callee::Decl(id),
                ..
            } => Some(p.decl(*id)),
            _ => None,
        })
        .unwrap();
    assert!(lame.prelude && lame.name == "lame_lambda");
}

#[test]
fn expressions_carry_their_types_and_numbers_are_si() {
    let p = program("let a = 2 kPa * 3\nlet b = [1, 2, 3] mm\nlet c = (4 mm)\n");
    let DeclKind::Let(a) = &user(&p, "a").kind else {
        panic!()
    };
    let pressure = crate::sema::units::unit("Pa").unwrap().1;
    assert_eq!(a.ty, crate::sema::types::Ty::scalar(pressure));
    let ExprKind::Binary { lhs, .. } = &a.kind else {
        panic!()
    };
    assert_eq!(lhs.kind, ExprKind::Num(2000.0));
    let DeclKind::Let(b) = &user(&p, "b").kind else {
        panic!()
    };
    assert_eq!(b.ty, crate::sema::types::Ty::vec3(Dim::LENGTH));
    assert!(matches!(b.kind, ExprKind::Array { scale, .. } if scale == 1e-3));
    // Parentheses only group.
    let DeclKind::Let(c) = &user(&p, "c").kind else {
        panic!()
    };
    assert_eq!(c.kind, ExprKind::Num(4.0 * 1e-3));
}

/// On every example, every expression lowering and the driver read has the checker's type
/// (none was skipped), and every declaration, sim statement, loss and optimize block is there.
#[test]
fn every_example_is_checked_into_a_typed_program() {
    for (path, text) in crate::example_scripts() {
        let ast = crate::front::parse(&text).unwrap();
        let (c, _) = crate::sema::check(&ast, &Default::default());
        let p = c.program;
        let name = path.display();
        let mut exprs = Vec::new();
        for d in &p.decls {
            match &d.kind {
                DeclKind::Mesh(e)
                | DeclKind::Region(e)
                | DeclKind::Chamber(e)
                | DeclKind::Obstacle(e)
                | DeclKind::Nodes(e)
                | DeclKind::Elements(e)
                | DeclKind::Let(e) => walk(e, &mut exprs),
                DeclKind::Param(x) => walk(&x.init, &mut exprs),
                DeclKind::Input(x) => walk(&x.source, &mut exprs),
                DeclKind::Fn(f) => walk(&f.body, &mut exprs),
                DeclKind::Material(_) => {}
            }
        }
        if let Some(l) = &p.loss {
            walk(&l.value, &mut exprs);
        }
        assert!(p.has_sim, "{name}");
        let untyped: Vec<_> = exprs.iter().filter(|e| e.ty.is_error()).collect();
        assert!(untyped.is_empty(), "{name}: untyped {untyped:?}");
        assert_eq!(
            p.user_decls().count(),
            ast.items
                .iter()
                .filter(|i| crate::sema::SymKind::of_item(i).is_some())
                .count(),
            "{name}"
        );
    }
}
