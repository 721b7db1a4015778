//! The escape links are built on first use: a build leaves them out, the walks that read
//! them build them (and give the full stack's hits), sizes and equality do not depend on
//! whether they are built yet, and a two-level BVH keeps them right through new
//! transforms whether they were built or not.

use bvhtrace_core::flat::{self, escape_links, escape_links_len};
use bvhtrace_core::{
    BuildOptions, FlatBvh, Instance, InstancedBvh, TraceOptions, Traversal, Triangle, trace_rays,
};
use glam::{Affine3A, Vec3};

mod common;

fn sphere() -> Vec<Triangle> {
    common::uv_sphere(16, 1.0, Vec3::ZERO)
}

#[test]
fn a_build_leaves_the_links_out_and_the_walks_that_read_them_build_them() {
    let tris = sphere();
    let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    assert!(!bvh.has_escapes(), "FlatBvh::build built the escape links");
    let sizes = bvh.byte_sizes();
    assert_eq!(sizes.1, escape_links_len(bvh.nodes().len()) * 4);
    let unbuilt = bvh.clone();
    // Checks neither need nor keep them.
    bvh.check_invariants().unwrap();
    bvh.check_escape_links().unwrap();
    assert!(!bvh.has_escapes());

    let rays = common::rays_for(&tris, 7, 2000);
    let full = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::FullStack)).hits;
    let wide = bvh.clone().with_wide();
    assert_eq!(
        trace_rays(&wide, &rays, &TraceOptions::closest(Traversal::Wide)).hits,
        full
    );
    assert!(
        !bvh.has_escapes() && !wide.has_escapes(),
        "the full-stack or wide walk built the escape links"
    );
    for tr in [Traversal::Stackless, Traversal::ShortStack(2)] {
        let hits = trace_rays(&bvh, &rays, &TraceOptions::closest(tr)).hits;
        assert_eq!(hits, full, "{tr}");
        assert!(bvh.has_escapes(), "{tr}");
    }
    assert_eq!(bvh.escapes(), escape_links(bvh.nodes()));
    assert_eq!(bvh.byte_sizes(), sizes);
    bvh.check_invariants().unwrap();

    // Clones before and after, and equality either way round.
    let built = bvh.clone();
    assert!(built.has_escapes() && !unbuilt.has_escapes());
    assert_eq!(built, unbuilt);
    assert_eq!(unbuilt, built);
    assert_eq!(built.escapes(), unbuilt.clone().escapes());
    assert!(!unbuilt.has_escapes(), "comparing built the links");

    // Set by hand and wrong: unequal, refused, and built anew on request.
    let mut wrong = built.clone();
    wrong.escapes_mut()[flat::escape_index(1, 0)] ^= 1;
    assert_ne!(wrong, unbuilt);
    assert_ne!(unbuilt, wrong);
    assert!(wrong.check_invariants().is_err());
    wrong.build_escapes();
    assert_eq!(wrong, unbuilt);
    let mut short = unbuilt.clone();
    short.set_escapes(vec![flat::NO_ESCAPE; 8]);
    let e = short.check_escape_links().unwrap_err();
    assert_eq!(
        (e.found, e.expected),
        (8, escape_links_len(bvh.nodes().len()))
    );
    short.clear_escapes();
    assert!(!short.has_escapes());
    short.check_escape_links().unwrap();
    assert_eq!(short, built);
    let mut made = unbuilt.clone();
    assert_eq!(
        made.escapes_mut().len(),
        escape_links_len(bvh.nodes().len())
    );
    assert!(made.has_escapes());
    assert!(unbuilt.clone().with_escapes().has_escapes());
}

#[test]
fn new_transforms_leave_unbuilt_links_unbuilt_and_right_once_built() {
    let tris = sphere();
    let instances: Vec<Instance> = (0..5)
        .map(|k| Instance::new(0, Affine3A::from_translation(Vec3::X * 2.5 * k as f32)))
        .collect();
    let mut ib = InstancedBvh::build(
        std::slice::from_ref(&tris),
        instances.clone(),
        &BuildOptions::default(),
    )
    .unwrap();
    assert!(!ib.bvh().has_escapes());
    let moved: Vec<Affine3A> = instances
        .iter()
        .enumerate()
        .map(|(k, i)| Affine3A::from_rotation_y(0.3 * k as f32) * i.transform)
        .collect();
    ib.set_transforms(&moved).unwrap();
    assert!(!ib.bvh().has_escapes(), "set_transforms built the links");
    ib.bvh().check_invariants().unwrap();
    // Built now, over both levels; another move rewrites the top level's in place.
    assert_eq!(ib.bvh().escapes(), escape_links(ib.bvh().nodes()));
    let back: Vec<Affine3A> = instances.iter().map(|i| i.transform).collect();
    ib.set_transforms(&back).unwrap();
    assert!(ib.bvh().has_escapes());
    assert_eq!(ib.bvh().escapes(), escape_links(ib.bvh().nodes()));
    ib.bvh().check_invariants().unwrap();
    let world: Vec<Triangle> = back
        .iter()
        .flat_map(|m| tris.iter().map(move |t| t.map(|p| m.transform_point3(p))))
        .collect();
    let rays = common::rays_for(&world, 3, 2000);
    let full = trace_rays(
        ib.bvh(),
        &rays,
        &TraceOptions::closest(Traversal::FullStack),
    )
    .hits;
    for tr in [Traversal::Stackless, Traversal::ShortStack(2)] {
        assert_eq!(
            trace_rays(ib.bvh(), &rays, &TraceOptions::closest(tr)).hits,
            full,
            "{tr}"
        );
    }
    let fresh = InstancedBvh::build(&[tris], instances, &BuildOptions::default()).unwrap();
    assert_eq!(ib.bvh(), fresh.bvh());
}

#[test]
fn a_tree_whose_links_leave_it_is_refused_before_its_escape_links_are_made() {
    // Read-back or deserialised nodes may point anywhere: the check says which node,
    // where computing the escape links from them would index past the array.
    let bvh = FlatBvh::build(&sphere(), &BuildOptions::default()).unwrap();
    for bad in [u32::MAX, bvh.nodes().len() as u32, 1, 0] {
        let mut nodes = bvh.nodes().to_vec();
        nodes[0].right_or_first = bad;
        let broken = FlatBvh::from_parts(nodes, bvh.triangles().to_vec(), bvh.depth());
        let e = broken.check_invariants().unwrap_err();
        assert!(e.starts_with("node 0: bad children"), "{bad}: {e}");
    }
}

#[test]
fn a_tree_whose_stated_depth_is_not_its_own_is_refused() {
    // The walks size their stacks by the depth: one stated too small would overflow them.
    let bvh = FlatBvh::build(&sphere(), &BuildOptions::default()).unwrap();
    assert!(bvh.check_invariants().is_ok());
    for wrong in [0, bvh.depth() - 1, bvh.depth() + 1] {
        let parts = FlatBvh::from_parts(bvh.nodes().to_vec(), bvh.triangles().to_vec(), wrong);
        let e = parts.check_invariants().unwrap_err();
        assert_eq!(e, format!("depth {wrong} stated, {} found", bvh.depth()));
    }
}
