//! The path tracer's kernel, validated by naga without a device after every library it
//! can be composed after, and its Rust types checked against its WGSL structs.

use bvhtrace_core::Traversal;
use bvhtrace_engine::{BvhStorage, LibraryShape, wgsl_library};
use bvhtrace_path::wavefront::{PathState, WaveParams, wavefront_source};
use bvhtrace_path::{PathLight, PathMaterial, PathParams, kernel_source};

fn module(shape: LibraryShape) -> naga::Module {
    validated(shape, &kernel_source())
}

/// `kernel` composed after the library of `shape`, parsed and validated.
fn validated(shape: LibraryShape, kernel: &str) -> naga::Module {
    let source = format!("{}\n{}", wgsl_library(shape, 0).source(), kernel);
    let module = naga::front::wgsl::parse_str(&source)
        .unwrap_or_else(|e| panic!("{shape}: {}", e.emit_to_string(&source)));
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::all(),
    )
    .validate(&module)
    .unwrap_or_else(|e| panic!("{shape}: {}", e.emit_to_string(&source)));
    module
}

/// Every shape of upload the tracer runs over: each storage, walk, masks or not, and the
/// device's ray queries.
fn shapes() -> Vec<LibraryShape> {
    let mut out = Vec::new();
    for storage in [BvhStorage::Buffers, BvhStorage::Textures] {
        for traversal in Traversal::all_with_short_stacks(&[6]) {
            for masks in [false, true] {
                out.push(LibraryShape {
                    masks,
                    ..LibraryShape::new(storage, false, traversal)
                });
            }
        }
    }
    for masks in [false, true] {
        out.push(LibraryShape {
            masks,
            ..LibraryShape::ray_queries(false)
        });
    }
    out
}

#[test]
fn the_kernel_validates_after_every_library() {
    let shapes = shapes();
    assert!(shapes.len() >= 18, "{} shapes", shapes.len());
    for shape in shapes {
        let m = module(shape);
        assert!(
            m.entry_points.iter().any(|e| e.name == "path_main"),
            "{shape}: no path_main"
        );
    }
}

#[test]
fn the_waves_validate_after_every_library() {
    let source = wavefront_source();
    for shape in shapes() {
        let m = validated(shape, &source);
        for entry in ["path_wave_start", "path_wave_extend"] {
            assert!(
                m.entry_points.iter().any(|e| e.name == entry),
                "{shape}: no {entry}"
            );
        }
    }
    // The step between waves is a module of its own.
    let prepare = bvhtrace_engine::shaders::PATH_WAVE_PREPARE.1;
    let m = naga::front::wgsl::parse_str(prepare).expect("path_wave_prepare.wgsl parses");
    naga::valid::Validator::new(
        naga::valid::ValidationFlags::all(),
        naga::valid::Capabilities::empty(),
    )
    .validate(&m)
    .expect("path_wave_prepare.wgsl validates");
}

/// `(name, offset)` of each member of WGSL struct `name`, and its size.
fn layout(m: &naga::Module, name: &str) -> (Vec<(String, u32)>, u32) {
    let (_, ty) = (m.types.iter())
        .find(|(_, t)| t.name.as_deref() == Some(name))
        .unwrap_or_else(|| panic!("no struct {name}"));
    let naga::TypeInner::Struct { members, span } = &ty.inner else {
        panic!("{name} is not a struct");
    };
    let fields = (members.iter())
        .map(|f| (f.name.clone().unwrap_or_default(), f.offset))
        .collect();
    (fields, *span)
}

#[test]
fn the_rust_types_are_the_wgsl_structs() {
    use std::mem::{offset_of, size_of};
    let m = module(LibraryShape::new(
        BvhStorage::Buffers,
        false,
        Traversal::Stackless,
    ));
    let check = |name: &str, size: usize, rust: &[(&str, usize)]| {
        let (wgsl, span) = layout(&m, name);
        assert_eq!(span as usize, size, "{name}: size");
        let wgsl: Vec<(String, usize)> = wgsl.into_iter().map(|(n, o)| (n, o as usize)).collect();
        for (field, offset) in rust {
            assert!(
                wgsl.iter().any(|(n, o)| n == field && o == offset),
                "{name}.{field}: Rust offset {offset}, WGSL {wgsl:?}"
            );
        }
    };
    check(
        "PathParams",
        size_of::<PathParams>(),
        &[
            ("eye", offset_of!(PathParams, eye)),
            ("tan_half_fov", offset_of!(PathParams, tan_half_fov)),
            ("forward", offset_of!(PathParams, forward)),
            ("aspect", offset_of!(PathParams, aspect)),
            ("right", offset_of!(PathParams, right)),
            ("width", offset_of!(PathParams, width)),
            ("up", offset_of!(PathParams, up)),
            ("height", offset_of!(PathParams, height)),
            ("sun_dir", offset_of!(PathParams, sun_dir)),
            ("max_depth", offset_of!(PathParams, max_depth)),
            ("sun", offset_of!(PathParams, sun)),
            ("light_count", offset_of!(PathParams, light_count)),
            ("env", offset_of!(PathParams, env)),
            ("sample", offset_of!(PathParams, sample)),
            ("seed", offset_of!(PathParams, seed)),
            ("material_count", offset_of!(PathParams, material_count)),
            ("prim_count", offset_of!(PathParams, prim_count)),
        ],
    );
    check(
        "PathMaterial",
        size_of::<PathMaterial>(),
        &[
            ("diffuse", offset_of!(PathMaterial, diffuse)),
            ("alpha2", offset_of!(PathMaterial, alpha2)),
            ("f0", offset_of!(PathMaterial, f0)),
            ("p_spec", offset_of!(PathMaterial, p_spec)),
            ("f0c", offset_of!(PathMaterial, f0c)),
            ("alpha2_m1", offset_of!(PathMaterial, alpha2_m1)),
            ("emissive", offset_of!(PathMaterial, emissive)),
            ("one_m_alpha2", offset_of!(PathMaterial, one_m_alpha2)),
            ("p_diffuse", offset_of!(PathMaterial, p_diffuse)),
            ("base_alpha", offset_of!(PathMaterial, base_alpha)),
            ("base_tex", offset_of!(PathMaterial, base_tex)),
            ("mr_tex", offset_of!(PathMaterial, mr_tex)),
            ("base_factor", offset_of!(PathMaterial, base_factor)),
            ("emissive_tex", offset_of!(PathMaterial, emissive_tex)),
            ("emissive_factor", offset_of!(PathMaterial, emissive_factor)),
            ("table", offset_of!(PathMaterial, table)),
        ],
    );
    check(
        "PathLight",
        size_of::<PathLight>(),
        &[
            ("v0", offset_of!(PathLight, v0)),
            ("cdf", offset_of!(PathLight, cdf)),
            ("e1", offset_of!(PathLight, e1)),
            ("pdf_area", offset_of!(PathLight, pdf_area)),
            ("e2", offset_of!(PathLight, e2)),
            ("prim", offset_of!(PathLight, prim)),
            ("emission", offset_of!(PathLight, emission)),
        ],
    );
    let m = validated(
        LibraryShape::new(BvhStorage::Buffers, false, Traversal::Stackless),
        &wavefront_source(),
    );
    let (wgsl, span) = layout(&m, "PathState");
    assert_eq!(span as usize, size_of::<PathState>(), "PathState: size");
    let rust = [
        ("origin", offset_of!(PathState, origin)),
        ("depth", offset_of!(PathState, depth)),
        ("dir", offset_of!(PathState, dir)),
        ("last_pdf", offset_of!(PathState, last_pdf)),
        ("throughput", offset_of!(PathState, throughput)),
        ("key", offset_of!(PathState, key)),
        ("last_n", offset_of!(PathState, last_n)),
        ("count", offset_of!(PathState, count)),
        ("radiance", offset_of!(PathState, radiance)),
    ];
    for (field, offset) in rust {
        assert!(
            wgsl.iter()
                .any(|(n, o)| n == field && *o as usize == offset),
            "PathState.{field}: Rust offset {offset}, WGSL {wgsl:?}"
        );
    }
    let (wgsl, span) = layout(&m, "PathWave");
    assert_eq!(span as usize, size_of::<WaveParams>(), "PathWave: size");
    let rust = [
        ("first_row", offset_of!(WaveParams, first_row)),
        ("rows", offset_of!(WaveParams, rows)),
        ("capacity", offset_of!(WaveParams, capacity)),
    ];
    for (field, offset) in rust {
        assert!(
            wgsl.iter()
                .any(|(n, o)| n == field && *o as usize == offset),
            "PathWave.{field}: Rust offset {offset}, WGSL {wgsl:?}"
        );
    }
}
