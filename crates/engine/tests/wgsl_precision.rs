//! The precision variants of the kernels (`bvhtrace_core::Precision`), without a GPU: each
//! composed module contains exactly its own triangle file, parses, validates (f64 only
//! with naga's `FLOAT64` capability, which `SHADER_F64` grants) and compiles to SPIR-V for
//! every entry point.

use bvhtrace_core::{Precision, Query, TraceOptions, Traversal};
use bvhtrace_engine::compose::{
    Entries, ModuleSet, kernel_source, kernel_source_for, triangle_wgsl,
};
use bvhtrace_engine::{BvhStorage, KernelKey};
use naga::valid::{Capabilities, ValidationFlags, Validator};

mod common;
use common::{SHARED_FILES, compile_variant, parse, validate_with};

const STORAGES: [BvhStorage; 2] = [BvhStorage::Buffers, BvhStorage::Textures];

fn capabilities(p: Precision) -> Capabilities {
    if p.needs_f64() {
        Capabilities::default() | Capabilities::FLOAT64
    } else {
        Capabilities::default()
    }
}

#[test]
fn each_precision_composes_its_own_triangle_module() {
    let names: Vec<&str> = Precision::ALL.iter().map(|&p| triangle_wgsl(p).0).collect();
    assert_eq!(
        names,
        [
            "triangle.wgsl",
            "triangle_moller_trumbore.wgsl",
            "triangle_f64.wgsl"
        ]
    );
    for storage in STORAGES {
        assert_eq!(
            kernel_source(storage),
            kernel_source_for(storage, Precision::WatertightF32),
            "the default precision is the default kernel"
        );
        for p in Precision::ALL {
            let src = kernel_source_for(storage, p);
            for q in Precision::ALL {
                let marker = format!("// ---- {} ----", triangle_wgsl(q).0);
                assert_eq!(src.contains(&marker), p == q, "{p}: {}", triangle_wgsl(q).0);
            }
            // Everything else is shared: every other file is composed once.
            for (name, _) in SHARED_FILES.iter().filter(|(n, _)| *n != "triangle.wgsl") {
                assert_eq!(
                    src.matches(&format!("// ---- {name} ----")).count(),
                    1,
                    "{p}: {name}"
                );
            }
            assert_eq!(src.matches("fn bvh_intersect_triangle(").count(), 1, "{p}");
        }
    }
}

#[test]
fn f64_needs_the_float64_capability() {
    let module = parse(&kernel_source_for(
        BvhStorage::Buffers,
        Precision::WatertightF64,
    ));
    let err = Validator::new(ValidationFlags::all(), Capabilities::default()).validate(&module);
    assert!(err.is_err(), "f64 validated without FLOAT64");
}

#[test]
fn every_precision_variant_validates_and_compiles() {
    let mut n = 0;
    for storage in STORAGES {
        for p in Precision::ALL {
            let module = parse(&kernel_source_for(storage, p));
            let info = validate_with(&module, capabilities(p));
            // The wide walk's module, its layout in the same storage.
            let wide_src = ModuleSet::wide_in(storage, p, Entries::All).compose(0);
            for q in Precision::ALL {
                let marker = format!("// ---- {} ----", triangle_wgsl(q).0);
                assert_eq!(wide_src.contains(&marker), p == q, "wide {p}: {marker}");
            }
            let nodes = format!("// ---- {} ----", storage.wide_wgsl().0);
            assert!(wide_src.contains(&nodes), "wide {p} {storage:?}");
            let wide = parse(&wide_src);
            let wide_info = validate_with(&wide, capabilities(p));
            for tr in [
                Traversal::FullStack,
                Traversal::Stackless,
                Traversal::ShortStack(6),
                Traversal::Wide,
            ] {
                for q in [Query::Closest, Query::Any] {
                    for counters in [false, true] {
                        let opts = TraceOptions::new(tr, q)
                            .with_precision(p)
                            .with_counters(counters);
                        let v = KernelKey::new(storage, &opts);
                        assert_eq!((v.precision, v.storage), (p, storage));
                        if tr == Traversal::Wide {
                            compile_variant(&wide, &wide_info, &v);
                        } else {
                            compile_variant(&module, &info, &v);
                        }
                        n += 1;
                    }
                }
            }
        }
    }
    assert_eq!(n, 2 * 3 * 4 * 2 * 2);
}
