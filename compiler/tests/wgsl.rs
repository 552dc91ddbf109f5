//! The WGSL backend: every generated module is valid WGSL for naga (f32, and f64 with
//! `FLOAT64`), for every kind of argument, domain and operation the IR has, and for script
//! names that clash with WGSL's reserved words; malformed kernels are refused with a message.
//! (The examples' modules are validated by the golden tests; running them is
//! `runtime/tests/gpu.rs`.)

use softc_compiler::back::{Precision, wgsl};
use softc_compiler::ir::{ArgSource, BinOp, CmpOp, Domain, KernelBuilder, Module, UnOp};

/// A module with kernels over every domain, reading through every argument source and using
/// every operation.
fn everything() -> Module {
    let mut m = Module::default();
    let x = m.buffer("x", Domain::Node, 3, "positions");
    let ef = m.buffer("elem_force", Domain::Element, 12, "");
    let tf = m.buffer("tri_force", Domain::Triangle, 9, "");
    let out = m.buffer("out", Domain::Node, 2, "");
    let s = m.buffer("total", Domain::Single, 1, "");
    let w1 = m.buffer("weights", Domain::Element, 1, "");

    // Element kernel: corners, own, uniforms, all unary/binary/compare ops, select.
    let mut k = KernelBuilder::new("elem", Domain::Element, "material test");
    let a = k.load(ArgSource::Corner {
        buffer: x,
        corner: 3,
        component: 2,
    });
    let b = k.load(ArgSource::Own {
        buffer: w1,
        component: 0,
    });
    let t = k.uniform("t");
    let p = k.uniform("param.w.1.3");
    let mut acc = k.b.add(a, b);
    for op in [
        UnOp::Neg,
        UnOp::Abs,
        UnOp::Sqrt,
        UnOp::Cbrt,
        UnOp::Exp,
        UnOp::Ln,
        UnOp::Sin,
        UnOp::Cos,
        UnOp::Tan,
        UnOp::Tanh,
        UnOp::Floor,
        UnOp::Ceil,
    ] {
        let u = k.b.un(op, acc);
        acc = k.b.add(acc, u);
    }
    for op in [
        BinOp::Sub,
        BinOp::Mul,
        BinOp::Div,
        BinOp::Pow,
        BinOp::Min,
        BinOp::Max,
    ] {
        let u = k.b.bin(op, acc, t);
        acc = k.b.add(acc, u);
    }
    for op in [
        CmpOp::Lt,
        CmpOp::Le,
        CmpOp::Gt,
        CmpOp::Ge,
        CmpOp::Eq,
        CmpOp::Ne,
    ] {
        let c = k.b.cmp(op, acc, p);
        acc = k.b.select(c, acc, t);
    }
    let inf = k.b.constant(f64::INFINITY);
    let big = k.b.constant(1e300);
    let acc2 = k.b.bin(BinOp::Min, acc, inf);
    let acc3 = k.b.bin(BinOp::Max, acc2, big);
    for c in 0..12 {
        k.store(ef, c, acc3);
    }
    k.store(w1, 0, acc);
    m.push_kernel(k.finish());

    // Triangle kernel.
    let mut k = KernelBuilder::new("pressure_cavity", Domain::Triangle, "pressure cavity");
    let a = k.load(ArgSource::Corner {
        buffer: x,
        corner: 2,
        component: 0,
    });
    let p = k.uniform("param.p_peak");
    let v = k.b.mul(a, p);
    for c in 0..9 {
        k.store(tf, c, v);
    }
    m.push_kernel(k.finish());

    // Node kernel: gathers over both CSR lists.
    let mut k = KernelBuilder::new("integrate", Domain::Node, "sim");
    let g1 = k.load(ArgSource::Gather {
        buffer: ef,
        over: Domain::Element,
        stride: 3,
        component: 1,
    });
    let g2 = k.load(ArgSource::Gather {
        buffer: tf,
        over: Domain::Triangle,
        stride: 3,
        component: 2,
    });
    let g3 = k.load(ArgSource::Gather {
        buffer: w1,
        over: Domain::Element,
        stride: 0,
        component: 0,
    });
    let own = k.load(ArgSource::Own {
        buffer: x,
        component: 1,
    });
    let s1 = k.b.add(g1, g2);
    let s2 = k.b.add(g3, own);
    k.store(out, 0, s1);
    k.store(out, 1, s2);
    m.push_kernel(k.finish());

    // Single kernel.
    let mut k = KernelBuilder::new("reduce", Domain::Single, "loss");
    let a = k.load(ArgSource::Own {
        buffer: s,
        component: 0,
    });
    let d = k.uniform("dt");
    let v = k.b.mul(a, d);
    k.store(s, 0, v);
    m.push_kernel(k.finish());
    m
}

#[test]
fn a_batched_module_offsets_every_buffer_by_its_scene_and_validates() {
    let m = everything();
    for p in [Precision::F32, Precision::F64] {
        let w = wgsl::emit_batched(&m, p, 4).unwrap();
        if let Err(e) = wgsl::validate(&w.source, p) {
            panic!("{p}: {e}\n{}", w.source);
        }
        assert_eq!(w.batch, Some(4));
        // Four launch blocks per binding, one per workgroup row z.
        assert!(
            w.source
                .contains("var<uniform> launch_elem: array<Launch_elem, 4>;")
        );
        assert!(w.source.contains("let l = &launch_elem[gid.z];"));
        // Scene, then the three entity counts, then the uniforms (aligned to a real).
        let k = &w.kernels[0];
        assert_eq!(k.uniform_offset, 24);
        assert_eq!(k.launch_size, 24 + 2 * p.size() as u64);
        // Node data through a corner, element data of the scene's own element.
        assert!(
            w.source
                .contains("let base_node = (*l).scene * (*l).nodes;")
        );
        // A node's 3-vector is one `vec4` load.
        assert!(w.source.contains("let q0 = x[(base_node + n3)];"));
        assert!(w.source.contains("let arg0 = q0.z;"));
        assert!(w.source.contains("weights[(base_element + e)]"));
        // Connectivity is shared: indexed by the scene-local entity.
        assert!(w.source.contains("elem_conn[4u * e + 3u]"));
        assert!(w.source.contains("for (var j = node_elem_offsets[e]"));
        // A per-corner 3-vector is gathered as the `vec4` of its slot past its scene's rows;
        // a per-element value needs the element of the slot.
        assert!(
            w.source
                .contains("let g0 = elem_force[4u * base_element + slot];")
        );
        assert!(w.source.contains("arg0 += g0.y;"));
        // A corner's force is one `vec4` store (the unused lane 0).
        assert!(
            w.source
                .contains("elem_force[4u * (base_element + e) + 3u] = vec4<real>(v56, v56, v56, ")
        );
        assert!(w.source.contains("weights[(base_element + ent)]"));
        assert!(wgsl::emit_batched(&m, p, 0).is_err());
    }
}

#[test]
fn every_argument_source_domain_and_operation_validates_in_f32_and_f64() {
    let m = everything();
    for p in [Precision::F32, Precision::F64] {
        let w = wgsl::emit(&m, p).unwrap();
        if let Err(e) = wgsl::validate(&w.source, p) {
            panic!("{p}: {e}\n{}", w.source);
        }
        assert_eq!(w.kernels.len(), 4);
        let integ = &w.kernels[2];
        // Gathers bind both CSR lists, and the three gathered buffers.
        assert_eq!(integ.storage_buffers, 3 + 1 + 1 + 4);
        let names: Vec<&str> = w.kernels[0]
            .uniforms
            .iter()
            .map(|&u| m.uniform_name(u))
            .collect();
        assert_eq!(names, ["t", "param.w.1.3"]);
        assert_eq!(w.kernels[0].launch_size, 8 + 2 * p.size() as u64);
        // Each gather loop sums in CSR order, once per CSR list.
        assert_eq!(
            w.source
                .matches("for (var j = node_elem_offsets[e]")
                .count(),
            1
        );
        assert_eq!(
            w.source.matches("for (var j = node_tri_offsets[e]").count(),
            1
        );
        // The declaration that produced a kernel is named above it.
        assert!(
            w.source.contains(
                "// ======== kernel pressure_cavity over triangle (from pressure cavity)"
            )
        );
        // Non-finite constants have no literal.
        assert!(w.source.contains("softc_inf()"));
        if p == Precision::F64 {
            for f in [
                "softc_exp",
                "softc_ln",
                "softc_sincos",
                "softc_tanh",
                "softc_pow",
            ] {
                assert!(w.source.contains(&format!("fn {f}(")), "{f}");
            }
            assert!(!w.source.contains(" exp(") && !w.source.contains(" log("));
        } else {
            // Native exp (its error is relative); ln, pow and cbrt in software: Vulkan's
            // log/log2 (and pow = exp2(b log2 a)) may be off by 2^-21 absolute near 1.
            assert!(w.source.contains(" exp("));
            for f in ["softc_ln", "softc_pow", "softc_cbrt"] {
                assert!(w.source.contains(&format!("fn {f}(")), "{f}");
            }
            assert!(!w.source.contains("log(") && !w.source.contains("log2("));
            assert_eq!(
                w.source.matches("pow(").count(),
                w.source.matches("softc_pow(").count(),
                "no native pow"
            );
        }
    }
    // Without FLOAT64, naga refuses the f64 module: validation is real.
    let w = wgsl::emit(&m, Precision::F64).unwrap();
    assert!(wgsl::validate(&w.source, Precision::F32).is_err());
}

#[test]
fn names_that_are_wgsl_words_are_renamed() {
    let mut m = Module::default();
    let a = m.buffer("var", Domain::Node, 1, "");
    let b = m.buffer("v1", Domain::Node, 1, "");
    let c = m.buffer("launch_x", Domain::Node, 1, "");
    let mut k = KernelBuilder::new("loop", Domain::Node, "odd names");
    let x = k.load(ArgSource::Own {
        buffer: a,
        component: 0,
    });
    let y = k.load(ArgSource::Own {
        buffer: b,
        component: 0,
    });
    let u = k.uniform("struct");
    let s = k.b.add(x, y);
    let s = k.b.add(s, u);
    k.store(c, 0, s);
    m.push_kernel(k.finish());
    let mut k = KernelBuilder::new("var", Domain::Node, "clashes with a buffer");
    let x = k.load(ArgSource::Own {
        buffer: a,
        component: 0,
    });
    k.store(c, 0, x);
    m.push_kernel(k.finish());
    for p in [Precision::F32, Precision::F64] {
        let w = wgsl::emit(&m, p).unwrap();
        wgsl::validate(&w.source, p).unwrap_or_else(|e| panic!("{e}\n{}", w.source));
        assert_eq!(w.kernels[0].entry, "loop_");
        assert_ne!(w.kernels[1].entry, "var_");
    }
}

#[test]
fn malformed_kernels_are_refused_with_a_message() {
    let mut m = Module::default();
    let x = m.buffer("x", Domain::Node, 3, "");
    let mut k = KernelBuilder::new("bad", Domain::Node, "test");
    let a = k.load(ArgSource::Corner {
        buffer: x,
        corner: 0,
        component: 0,
    });
    k.store(x, 0, a);
    m.push_kernel(k.finish());
    let e = wgsl::emit(&m, Precision::F32).unwrap_err();
    assert!(e.contains("kernel `bad`") && e.contains("corner"), "{e}");

    let mut m = Module::default();
    let x = m.buffer("x", Domain::Node, 3, "");
    let mut k = KernelBuilder::new("wide", Domain::Node, "test");
    let a = k.load(ArgSource::Own {
        buffer: x,
        component: 3,
    });
    k.store(x, 0, a);
    m.push_kernel(k.finish());
    let e = wgsl::emit(&m, Precision::F32).unwrap_err();
    assert!(e.contains("component 3"), "{e}");
}

#[test]
fn constants_are_exact_in_their_precision() {
    let mut m = Module::default();
    let x = m.buffer("x", Domain::Single, 1, "");
    let mut k = KernelBuilder::new("c", Domain::Single, "constants");
    let a = k.load(ArgSource::Own {
        buffer: x,
        component: 0,
    });
    let c = k.b.constant(0.1);
    let v = k.b.mul(a, c);
    let nan = k.b.constant(f64::NAN);
    let v = k.b.add(v, nan);
    k.store(x, 0, v);
    m.push_kernel(k.finish());
    let f32s = wgsl::emit(&m, Precision::F32).unwrap().source;
    let f64s = wgsl::emit(&m, Precision::F64).unwrap().source;
    assert!(f32s.contains("0.1f"), "{f32s}");
    assert!(f64s.contains("0.1lf"), "{f64s}");
    assert!(f64s.contains("softc_nan()"));
    wgsl::validate(&f64s, Precision::F64).unwrap();
}

#[test]
fn rows_of_three_vectors_lie_as_vec4s_and_round_trip() {
    use softc_compiler::back::wgsl::RowLayout;
    // Plain rows stay as they are.
    for w in [1, 2] {
        let l = RowLayout::of(w);
        assert!(!l.is_vector());
        assert_eq!(l.padded(), w);
    }
    // A node's 3-vector; a tet's four corner forces; a rest shape of 7 values.
    let node = RowLayout::of(3);
    assert_eq!((node.lanes, node.groups(), node.padded()), (3, 1, 4));
    let corners = RowLayout::of(12);
    assert_eq!(
        (corners.lanes, corners.groups(), corners.padded()),
        (3, 4, 16)
    );
    assert_eq!(corners.place(7), (2, 1));
    let shape = RowLayout::of(7);
    assert_eq!((shape.lanes, shape.groups(), shape.padded()), (4, 2, 8));
    assert_eq!(shape.place(6), (1, 2));
    // Two rows each: padded with zeros in the unused lanes, and back.
    let values: Vec<f64> = (0..24).map(f64::from).collect();
    let padded = corners.pad(&values);
    assert_eq!(padded.len(), 32);
    assert_eq!(&padded[..8], &[0.0, 1.0, 2.0, 0.0, 3.0, 4.0, 5.0, 0.0]);
    assert_eq!(&padded[16..20], &[12.0, 13.0, 14.0, 0.0]);
    assert_eq!(corners.unpad(padded.into_owned()), values);
    let values: Vec<f64> = (0..14).map(f64::from).collect();
    let padded = shape.pad(&values);
    assert_eq!(&padded[4..8], &[4.0, 5.0, 6.0, 0.0]);
    assert_eq!(shape.unpad(padded.into_owned()), values);
}

#[test]
fn corner_vectors_of_one_scene_lie_corner_major_and_round_trip() {
    use softc_compiler::back::wgsl::RowLayout;
    let corners = RowLayout {
        corner_major: true,
        ..RowLayout::of(12)
    };
    // Three tets' four corner forces: corner 1 of tet 2 (values 27..29) is `vec4` 1·3 + 2.
    let values: Vec<f64> = (0..36).map(f64::from).collect();
    let padded = corners.pad(&values);
    assert_eq!(padded.len(), 48);
    assert_eq!(&padded[20..24], &[27.0, 28.0, 29.0, 0.0]);
    assert_eq!(&padded[..8], &[0.0, 1.0, 2.0, 0.0, 12.0, 13.0, 14.0, 0.0]);
    assert_eq!(corners.unpad(padded.into_owned()), values);
}

#[test]
fn only_a_single_scenes_corner_vectors_are_corner_major() {
    use softc_compiler::back::wgsl::RowLayout;
    use softc_compiler::ir::BufferId;
    let module = everything();
    let named =
        |name: &str| BufferId(module.buffers.iter().position(|b| b.name == name).unwrap() as u32);
    let force = named("elem_force");
    assert!(RowLayout::of_buffer(&module, force, false).corner_major);
    assert!(!RowLayout::of_buffer(&module, force, true).corner_major);
    assert!(RowLayout::of_buffer(&module, named("tri_force"), false).corner_major);
    // Node rows and element rows that are not one vector per corner stay entity-major.
    assert!(!RowLayout::of_buffer(&module, named("x"), false).corner_major);
    assert!(!RowLayout::of_buffer(&module, named("weights"), false).corner_major);
    // Corner c of element e is `vec4` `c · rows + e`, where the element kernel stores it and
    // the node gather reads it.
    let one = wgsl::emit(&module, Precision::F32).unwrap();
    assert!(
        one.source
            .contains("let rows_elem_force = arrayLength(&elem_force) / 4u;")
    );
    assert!(one.source.contains("elem_force[3u * rows_elem_force + e]"));
    assert!(
        one.source
            .contains("elem_force[(slot % 4u) * rows_elem_force + slot / 4u]")
    );
    let batch = wgsl::emit_batched(&module, Precision::F32, 2).unwrap();
    assert!(!batch.source.contains("rows_elem_force"));
}
