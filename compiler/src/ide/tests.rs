//! Tests of the editor answers: hover, definition, outline, completion, odd text.

use super::*;
use crate::sema;

fn at(text: &str, needle: &str) -> usize {
    text.find(needle).expect("needle") + 1
}

#[test]
fn every_builtin_function_is_documented() {
    for f in sema::FUNCTIONS {
        assert!(
            BUILTIN_DOCS.iter().any(|b| b.name == *f),
            "built-in `{f}` has no entry in ide::BUILTIN_DOCS"
        );
    }
    for b in BUILTIN_DOCS {
        assert!(
            sema::FUNCTIONS.contains(&b.name),
            "`{}` is not a built-in",
            b.name
        );
    }
    for (c, _) in sema::CONSTANTS {
        assert!(CONSTANT_DOCS.iter().any(|(n, _)| n == c), "constant `{c}`");
    }
    for r in sema::RESERVED_NAMES {
        assert!(RESERVED_DOCS.iter().any(|(n, _)| n == r), "reserved `{r}`");
    }
}

/// The documented parameter names are the checker's: calling with them by name never
/// gives "unknown argument" (E0105).
#[test]
fn documented_parameter_names_are_accepted() {
    for b in BUILTIN_DOCS {
        for p in b.params {
            let src = format!("let _a = {}({p}: 1)\n", b.name);
            let checked = crate::check_source(&src, &Default::default());
            assert!(
                !checked.diagnostics.iter().any(|d| d.code == "E0105"),
                "`{}` rejects its documented parameter `{p}`: {:?}",
                b.name,
                checked.diagnostics
            );
        }
    }
}

#[test]
fn units_after_numbers_and_arrays_are_tokens() {
    let text = "let rho = 1070 kg/m^3\nlet g = [0, 0, -9.81] m/s^2 + 8 /s\nlet a = x[1] and 2";
    let toks = tokenize(text);
    let units: Vec<&str> = toks
        .iter()
        .filter(|t| t.kind == TokKind::Unit)
        .map(|t| &text[t.span.start..t.span.end])
        .collect();
    assert_eq!(units, ["kg", "m", "m", "s", "s"]);
}

#[test]
fn hover_shows_param_type_unit_and_bounds() {
    let text = "param p_max: pressure = 1 kPa in [0 kPa, 50 kPa]\nlet q = p_max * 2\n";
    let checked = crate::check_source(text, &Default::default());
    let a = Analysis::with_check(text, checked.script);
    let (h, _) = a.hover(text.rfind("p_max").unwrap() + 1).unwrap();
    assert!(
        h.contains("param p_max: pressure [Pa] = 1 kPa in [0 kPa, 50 kPa]"),
        "{h}"
    );
    let (h, _) = a.hover(at(text, "kPa")).unwrap();
    assert!(h.contains("1 kPa = 1000 Pa"), "{h}");
    let (h, _) = a.hover(at(text, "q =")).unwrap();
    assert!(h.contains("let q: pressure [Pa]"), "{h}");
    let text = "let s = sphere(center: [0, 0, 0] mm, radius: 2 mm)\nsim { dt = auto }\n";
    let a = Analysis::new(text);
    let (h, _) = a.hover(at(text, "radius")).unwrap();
    assert!(h.contains("argument `radius` of `sphere`"), "{h}");
    let (h, _) = a.hover(at(text, "auto")).unwrap();
    assert!(h.contains("built-in constant"), "{h}");
    let text = "let m = yeoh(c10: 1 kPa, d1: 1 /MPa, density: 1 kg/m^3)\n";
    let (h, _) = Analysis::new(text).hover(at(text, "d1")).unwrap();
    assert!(h.contains("material yeoh(c10: pressure"), "{h}");
}

#[test]
fn definition_of_chamber_in_pressure_statement() {
    let text = "chamber cavity = surface(body, \"c\")\nsim {\n  pressure cavity = 1 kPa\n}\n";
    let a = Analysis::new(text);
    let use_at = text.rfind("cavity").unwrap() + 2;
    let def = a.definition(use_at).unwrap();
    assert_eq!(&text[def.start..def.end], "cavity");
    assert_eq!(def.start, text.find("cavity").unwrap());
}

#[test]
fn definitions_of_locals_and_the_outline() {
    let text = "fn f(a: length, b: length = 1 mm) -> length = a + b\n\
                let s = sum(i in 0..3) i * 1 mm\n\
                region r = box(min: [0, 0, 0] mm, max: [1, 1, 1] mm)\n\
                sim {\n  let k = 2\n  damping = k * 1 /s\n  fix r\n}\n";
    let a = Analysis::new(text);
    let def_of = |needle: &str, skip: usize| {
        let at = text.match_indices(needle).nth(skip).unwrap().0;
        let d = a.definition(at).expect(needle);
        (d.start, &text[d.start..d.end])
    };
    // The fn parameter `a` in the body, the reduction variable, the sim let, the region.
    assert_eq!(def_of("a + b", 0), (text.find("a:").unwrap(), "a"));
    assert_eq!(def_of("b\n", 0), (text.find("b:").unwrap(), "b"));
    assert_eq!(def_of("i * 1", 0), (text.find("i in").unwrap(), "i"));
    assert_eq!(def_of("k * 1", 0), (text.find("k = 2").unwrap(), "k"));
    assert_eq!(def_of("r\n}", 0), (text.find("r = box").unwrap(), "r"));
    let h = a.hover(text.find("a + b").unwrap()).unwrap().0;
    assert!(
        h.contains("a: length [m]") && h.contains("parameter of `f`"),
        "{h}"
    );
    let outline: Vec<(String, &str, usize)> = a
        .symbols()
        .into_iter()
        .map(|s| (s.name, s.kind, s.children.len()))
        .collect();
    assert_eq!(
        outline,
        [
            ("f".to_string(), "fn", 0),
            ("s".to_string(), "let", 0),
            ("r".to_string(), "region", 0),
            ("sim".to_string(), "sim", 1)
        ]
    );
    // While the script does not parse, declarations are still found.
    let broken = format!("{text}let oops = (\n");
    let b = Analysis::new(&broken);
    assert!(b.script.is_none());
    let r_use = broken.find("fix r").unwrap() + 4;
    assert_eq!(
        b.definition(r_use),
        Some(Span::new(
            broken.find("r = box").unwrap(),
            broken.find("r = box").unwrap() + 1
        ))
    );
    assert!(b.symbols().iter().any(|s| s.name == "oops"));
    assert!(b.hover(r_use).unwrap().0.contains("region r = box"));
}

#[test]
fn completion_contexts() {
    let kw = |text: &str| -> Vec<String> {
        Analysis::new(text)
            .completions(text.len())
            .into_iter()
            .map(|c| c.label)
            .collect()
    };
    assert!(kw("mat").contains(&"material".to_string()));
    assert!(kw("let a = 3 k").contains(&"kPa".to_string()));
    assert!(kw("let a = [1, 2] m").contains(&"mm".to_string()));
    assert!(!kw("let a = x[1] m").contains(&"mm".to_string()));
    assert!(kw("let a = 8 /").contains(&"s".to_string()));
    assert!(kw("let a = 1070 kg/m").contains(&"mm".to_string()));
    assert!(!kw("let a = 8 / s").contains(&"ms".to_string()));
    assert!(!kw("let a = 8\n  m").contains(&"mm".to_string()));
    assert!(kw("sim {\n  da").contains(&"damping".to_string()));
    assert!(kw("optimize p with adam(lr: 0.1) {\n  ").contains(&"gradient_scale".to_string()));
    assert!(kw("param p: pre").contains(&"pressure".to_string()));
    assert!(kw("let a = adam(").contains(&"beta1".to_string()));
    assert!(kw("let a = yeoh(c10: 1 kPa, ").contains(&"density".to_string()));
    let names = kw("param pmax: pressure = 1 kPa\nlet b = 2 * pm");
    assert!(names.contains(&"pmax".to_string()), "{names:?}");
    assert!(kw("let b = sq").contains(&"sqrt".to_string()));
    let decls = "chamber ch = surface(b, \"c\")\nregion r = box(min: [0, 0, 0] mm, max: [1, 1, 1] mm)\nparam p: pressure = 1 kPa\nmaterial m = neo_hookean(mu: 1 kPa, kappa: 1 MPa, density: 1 kg/m^3)\nelements e = tagged(b, 1)\n";
    let names = |tail: &str| kw(&format!("{decls}{tail}"));
    assert_eq!(names("sim {\n  pressure "), ["ch"]);
    assert_eq!(names("sim {\n  fix "), ["r"]);
    assert_eq!(names("sim {\n  fix r, "), ["r"]);
    assert_eq!(names("sim {\n  use "), ["m"]);
    assert_eq!(names("sim {\n  use m in "), ["e"]);
    assert_eq!(names("optimize "), ["p"]);
    assert!(names("sim {\n  pressure ch = ").contains(&"p".to_string()));
}

/// Obstacles and contact: hover on the keywords, the shape, its and the statement's
/// arguments and the obstacle's name; definitions; completion of the names and arguments.
#[test]
fn obstacles_and_contact() {
    let text = "mesh body = load(\"b.msh\")\nnodes tip = select(body, x > 1 mm)\n\
                obstacle floor = plane(point: [0, 0, -1] mm, normal: [0, 0, 1])\n\
                sim {\n  integrator = quasi_static\n  \
                contact body with floor (gap: 0.1 mm, stiffness: 1 MPa)\n}\n";
    let a = Analysis::new(text);
    assert!(a.script.is_some());
    let hover = |needle: &str| a.hover(at(text, needle)).map(|h| h.0).unwrap_or_default();
    let h = hover("floor (");
    assert!(h.contains("obstacle floor = plane(point:"), "{h}");
    assert!(h.contains("an obstacle"), "{h}");
    let h = hover("plane(");
    assert!(h.contains("obstacle shape"), "{h}");
    let h = hover("point:");
    assert!(h.contains("argument `point` of `plane`"), "{h}");
    let h = hover("gap:");
    assert!(h.contains("argument `gap` of `contact`"), "{h}");
    assert!(h.contains("stiffness?: pressure"), "{h}");
    assert!(hover("stiffness:").contains("argument `stiffness` of `contact`"));
    assert!(hover("contact body").contains("keyword"));
    assert!(hover("obstacle floor").contains("keyword"));
    let def = a.definition(at(text, "floor (")).unwrap();
    assert_eq!(def.start, text.find("floor =").unwrap());
    assert_eq!(a.references(def.start).len(), 2);
    assert!(
        a.symbols()
            .iter()
            .any(|s| s.name == "floor" && s.kind == "obstacle")
    );
    // While the script does not parse, the obstacle is still found.
    let broken = format!("{text}let oops = (\n");
    let b = Analysis::new(&broken);
    assert!(b.script.is_none());
    assert_eq!(b.definition(at(&broken, "floor (")), Some(def));

    let kw = |text: &str| -> Vec<String> {
        Analysis::new(text)
            .completions(text.len())
            .into_iter()
            .map(|c| c.label)
            .collect()
    };
    let decls = "mesh body = load(\"b.msh\")\nnodes tip = select(body, x > 1 mm)\n\
                 region r = box(min: [0, 0, 0] mm, max: [1, 1, 1] mm)\n\
                 obstacle floor = plane(point: [0, 0, -1] mm, normal: [0, 0, 1])\n";
    let names = |tail: &str| kw(&format!("{decls}{tail}"));
    assert!(kw("obs").contains(&"obstacle".to_string()));
    assert!(names("sim {\n  con").contains(&"contact".to_string()));
    assert_eq!(
        names("obstacle ball = "),
        ["plane", "box", "sphere", "cylinder"]
    );
    assert_eq!(names("sim {\n  contact "), ["body", "tip"]);
    assert_eq!(names("sim {\n  contact tip with "), ["floor"]);
    // The statement's arguments first (then what a positional argument may be).
    let args = names("sim {\n  contact tip with floor (");
    assert_eq!(args[..2], ["gap", "stiffness"], "{args:?}");
    let args = names("sim {\n  contact tip with floor (gap: 1 mm, st");
    assert_eq!(args[0], "stiffness", "{args:?}");
    assert!(names("sim {\n  contact tip with floor (gap: 1 ").contains(&"mm".to_string()));
    assert_eq!(names("obstacle wall = plane(")[..2], ["point", "normal"]);
    // The same without a parse (the text ends inside the statement).
    let unparsed = "obstacle wall = plane(point: [0, 0, 0] mm, normal: [1, 0, 0])\n\
                    sim {\n  contact body with ";
    assert_eq!(kw(unparsed), ["wall"]);
}

#[test]
fn never_panics_on_odd_text() {
    for text in [
        "",
        "\"",
        "3 /",
        "[",
        "]] m",
        "µ",
        "1 µm",
        "let x = 3 kPa ^",
        "fn f(",
        "sim { let",
        "\u{feff}",
        "1e",
        "..",
        "3 m^-",
    ] {
        let a = Analysis::new(text);
        for o in 0..=text.len() + 1 {
            let _ = a.hover(o);
            let _ = a.definition(o);
            let _ = a.completions(o);
            let _ = a.references(o);
        }
        let _ = a.symbols();
    }
}

/// The resolution table is the checker's: on every example, each use names a declaration of
/// the same name, each declaration is where its name is written, no use is recorded twice, and
/// every declared global the checker saw used has a use in the table.
#[test]
fn the_checkers_resolution_table_is_consistent_on_every_example() {
    for (path, text) in crate::example_scripts() {
        let a = Analysis::new(&text);
        let r = &a.resolved;
        let name = path.display();
        assert!(!r.defs.is_empty() && !r.refs.is_empty(), "{name}");
        for d in &r.defs {
            assert_eq!(&text[d.span.start..d.span.end], d.name, "{name}: {d:?}");
        }
        let mut uses = std::collections::HashSet::new();
        for (span, d) in &r.refs {
            assert_eq!(
                &text[span.start..span.end],
                r.defs[*d].name,
                "{name}: {span:?}"
            );
            assert!(
                uses.insert((span.start, span.end)),
                "{name}: {span:?} twice"
            );
        }
        for f in &r.free {
            assert!(
                uses.insert((f.span.start, f.span.end)),
                "{name}: {f:?} also a use"
            );
        }
        // A global the checker does not warn about as unused (W0001) is used somewhere (but a
        // scene's only material, used without `use`).
        let report = crate::check_source(&text, &Default::default());
        let written =
            |d: &&Def| matches!(d.kind, DefKind::Global(k) if k != crate::sema::SymKind::Material);
        for d in r.defs.iter().filter(written) {
            let unused = report
                .diagnostics
                .iter()
                .any(|w| w.code == "W0001" && w.span == d.span);
            let used = r.refs.iter().any(|(_, i)| r.defs[*i].span == d.span);
            assert!(
                unused || used,
                "{name}: `{}` is used but the table has no use",
                d.name
            );
        }
    }
}

/// A script with semantic mistakes is still resolved: declarations and uses around an unknown
/// name, a type error and a wrong kind of name.
#[test]
fn a_script_with_errors_is_resolved_too() {
    let text = "param p: pressure = 1 kPa\nlet a = p + 2 mm\nlet b = a * nowhere\n\
                nodes tip = select(body, x > 1 mm)\nsim {\n  fix p\n  let k = b\n}\n";
    let a = Analysis::new(text);
    let def = |needle: &str| {
        let at = text.find(needle).unwrap();
        a.definition(at).map(|s| &text[s.start..s.end])
    };
    // `p` in `p + 2 mm` (a type error) and in `fix p` (a param is not a node set).
    assert_eq!(def("p + 2"), Some("p"));
    assert_eq!(def("p\n  let"), Some("p"));
    assert_eq!(def("a * nowhere"), Some("a"));
    assert_eq!(def("b\n}"), Some("b"));
    assert!(a.resolved.free.iter().any(|f| f.name == "nowhere"));
    assert!(a.resolved.free.iter().any(|f| f.name == "body"));
    let refs = a.references(text.find("p:").unwrap());
    assert_eq!(refs.len(), 3, "{refs:?}");
}
