//! The single-ray walks against the reference walk: random soups (slivers, degenerate
//! and duplicated triangles, huge offsets) and rays (axis-parallel, from inside boxes,
//! subnormal, with odd intervals), every builder, leaves small and large, every
//! instruction set.

use bvhtrace_core::{BuildOptions, BuilderKind, FlatBvh, Hit, INVALID_RAY, MISS, Query, Ray};
use bvhtrace_cpu::CpuBvh;
use glam::Vec3;
use proptest::prelude::*;

mod common;
use common::{every_isa, f32_departure, reference, same};

/// Checks every ray of `rays`: closest hits the reference's to the bit (or the documented
/// f32 departure), any-hit agreeing on hit or miss. Returns the departures.
fn check(
    tris: &[bvhtrace_core::Triangle],
    flat: &FlatBvh,
    rays: &[Ray],
) -> Result<usize, TestCaseError> {
    let bvh = CpuBvh::from_flat(flat).unwrap();
    let want = reference(flat, rays, Query::Closest);
    let got = every_isa(&bvh, rays, Query::Closest);
    let any = every_isa(&bvh, rays, Query::Any);
    let mut departures = 0;
    for (i, ray) in rays.iter().enumerate() {
        let (g, w) = (&got[i], &want[i]);
        if !same(g, w) {
            prop_assert!(
                f32_departure(tris, ray, g, w),
                "ray {i} {ray:?}: {g:?} vs reference {w:?}"
            );
            departures += 1;
        }
        prop_assert_eq!(
            any[i].is_hit(),
            g.is_hit(),
            "any-hit on ray {} {:?}",
            i,
            ray
        );
        if any[i].is_hit() {
            prop_assert!(any[i].t >= ray.t_min && any[i].t < ray.t_max);
        } else {
            prop_assert!(same(&any[i], g), "any-hit miss {:?} vs {:?}", any[i], g);
        }
    }
    Ok(departures)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(160))]

    #[test]
    fn closest_and_any_hits_are_the_reference_walks(
        tris in common::soup(),
        seed in any::<u64>(),
        b in 0usize..BuilderKind::ALL.len(),
        leaf in prop::sample::select(vec![1usize, 3, 8, 80]),
    ) {
        let opts = BuildOptions { max_leaf_size: leaf, ..BuildOptions::with_builder(BuilderKind::ALL[b]) };
        let flat = FlatBvh::build(&tris, &opts).unwrap();
        check(&tris, &flat, &common::rays_for(&tris, seed, 64))?;
    }
}

/// Exact ties: three copies of a triangle (the lowest id wins), and two triangles sharing
/// an edge hit on the edge (both at t = 5; the lower id wins).
#[test]
fn exact_ties_go_to_the_lower_primitive() {
    let t = [
        Vec3::new(-1.0, -1.0, 0.0),
        Vec3::new(1.0, -1.0, 0.0),
        Vec3::new(0.0, 1.0, 0.0),
    ];
    let mut tris = vec![
        [
            Vec3::splat(50.0),
            Vec3::splat(51.0),
            Vec3::new(50.0, 52.0, 50.0),
        ],
        t,
        t,
        t,
    ];
    tris.push([
        Vec3::new(-1.0, 0.0, 5.0),
        Vec3::new(1.0, 0.0, 5.0),
        Vec3::new(0.0, 1.0, 5.0),
    ]);
    tris.push([
        Vec3::new(1.0, 0.0, 5.0),
        Vec3::new(-1.0, 0.0, 5.0),
        Vec3::new(0.0, -1.0, 5.0),
    ]);
    for b in BuilderKind::ALL {
        for leaf in [1, 4, 8] {
            let opts = BuildOptions {
                max_leaf_size: leaf,
                ..BuildOptions::with_builder(b)
            };
            let bvh = CpuBvh::from_flat(&FlatBvh::build(&tris, &opts).unwrap()).unwrap();
            let rays = [
                Ray::new(Vec3::new(0.0, 0.0, -5.0), Vec3::Z),
                Ray::new(Vec3::new(0.0, 0.0, 10.0), -Vec3::Z),
            ];
            let h = every_isa(&bvh, &rays, Query::Closest);
            assert_eq!((h[0].prim, h[0].t), (1, 5.0), "{b:?} leaf {leaf}");
            assert_eq!((h[1].prim, h[1].t), (4, 5.0), "{b:?} leaf {leaf}");
        }
    }
}

/// Rays that cannot be traced, an empty interval and an empty tree: what the core walks
/// answer.
#[test]
fn untraceable_rays_and_empty_trees() {
    let tris = common::uv_sphere(6, 1.0, Vec3::ZERO);
    let flat = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let rays = [
        Ray::new(Vec3::new(f32::NAN, 0.0, -5.0), Vec3::Z),
        Ray::new(Vec3::new(0.0, 0.0, -5.0), Vec3::ZERO),
        Ray::with_interval(Vec3::new(0.0, 0.0, -5.0), Vec3::Z, 0.0, f32::NAN),
        Ray::with_interval(Vec3::new(0.0, 0.0, -5.0), Vec3::Z, 3.0, 2.0),
        Ray::with_interval(Vec3::new(0.0, 0.0, -5.0), Vec3::Z, 0.0, 4.0),
        Ray::new(Vec3::new(0.0, 0.0, -5.0), Vec3::Z),
    ];
    let bvh = CpuBvh::from_flat(&flat).unwrap();
    for q in [Query::Closest, Query::Any] {
        let got = every_isa(&bvh, &rays, q);
        let want = reference(&flat, &rays, q);
        // Alone too: a batch where no ray is walked takes a path of its own.
        let alone: Vec<Hit> = rays
            .iter()
            .map(|r| bvhtrace_cpu::trace_ray(&bvh, r, q))
            .collect();
        for (g, w) in got.iter().chain(&alone).zip(want.iter().cycle()) {
            assert_eq!(g.prim == INVALID_RAY, w.prim == INVALID_RAY);
            assert_eq!(g.is_hit(), w.is_hit());
            if q == Query::Closest || !g.is_hit() {
                assert!(same(g, w), "{g:?} vs {w:?}");
            }
        }
        assert!(got[5].is_hit() && !got[4].is_hit() && got[0].prim == INVALID_RAY);
    }
    let empty = CpuBvh::from_flat(&FlatBvh::default()).unwrap();
    let h = bvhtrace_cpu::trace_ray(&empty, &rays[5], Query::Closest);
    assert_eq!((h.prim, h.t), (MISS, f32::INFINITY));
}

/// Closed spheres at offsets up to 1e7 and scales 1e-9..1e9 leak no ray, and every hit
/// is the reference's to the bit.
#[test]
fn closed_meshes_leak_no_ray_at_any_offset_and_scale() {
    let mut checked = 0;
    for scale in [1e-9f32, 1e-4, 1.0, 1e4, 1e9] {
        for offset in [0.0f32, 1.0, 1e4, 1e7] {
            if scale < offset * 1e-4 {
                continue;
            }
            let c = Vec3::new(offset, -0.5 * offset, 0.25 * offset);
            let tris = common::uv_sphere(10, scale, c);
            let flat = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
            let bvh = CpuBvh::from_flat(&flat).unwrap();
            let mut rnd = common::xorshift(0x9e37_79b9_7f4a_7c15);
            let rays: Vec<Ray> = (0..400)
                .map(|_| {
                    let d = Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5);
                    let d = if d.length() < 1e-3 {
                        Vec3::X
                    } else {
                        d.normalize()
                    };
                    let aim = c + Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5) * scale;
                    Ray::new(aim - d * (3.0 * scale), d)
                })
                .collect();
            let want = reference(&flat, &rays, Query::Closest);
            for q in [Query::Closest, Query::Any] {
                let got = every_isa(&bvh, &rays, q);
                for (i, (g, w)) in got.iter().zip(&want).enumerate() {
                    assert!(g.is_hit(), "scale {scale} offset {offset}: ray {i} escaped");
                    if q == Query::Closest {
                        assert!(
                            same(g, w),
                            "scale {scale} offset {offset} ray {i}: {g:?} vs {w:?}"
                        );
                    }
                }
                checked += got.len();
            }
        }
    }
    assert_eq!(checked, 14 * 2 * 400);
}

/// A binary leaf too long for one leaf child is split into a node over runs of it, and
/// every triangle is still found: one leaf of 300 triangles.
#[test]
fn long_leaves_are_split() {
    let tris = common::uv_sphere(10, 1.0, Vec3::ZERO);
    assert!(tris.len() > 64 * 3);
    let opts = BuildOptions {
        max_leaf_size: 1000,
        cost_intersection: 1e-6,
        ..BuildOptions::default()
    };
    let flat = FlatBvh::build(&tris, &opts).unwrap();
    assert_eq!(flat.nodes().len(), 1, "expected one leaf");
    let bvh = CpuBvh::from_flat(&flat).unwrap();
    assert!(
        bvh.nodes().len() > 1 && bvh.depth() >= 2,
        "{} nodes",
        bvh.nodes().len()
    );
    let rays = common::rays_for(&tris, 5, 500);
    let want = reference(&flat, &rays, Query::Closest);
    let got = every_isa(&bvh, &rays, Query::Closest);
    let hits = got.iter().filter(|h| h.is_hit()).count();
    assert!(hits > 300, "{hits}");
    for (g, w) in got.iter().zip(&want) {
        assert!(same(g, w), "{g:?} vs {w:?}");
    }
}

/// The layout's sizes: 256-byte nodes, 160-byte blocks, and under the binary layout's
/// bytes per triangle on a closed mesh.
#[test]
fn layout_sizes() {
    assert_eq!(std::mem::size_of::<bvhtrace_cpu::Node8>(), 256);
    assert_eq!(std::mem::size_of::<bvhtrace_cpu::Tri4>(), 160);
    let tris = common::uv_sphere(60, 1.0, Vec3::ZERO);
    let flat = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let bvh = CpuBvh::from_flat(&flat).unwrap();
    let (n, _, t) = flat.byte_sizes();
    let binary = (n + t) as f64 / tris.len() as f64;
    let ours = bvh.bytes_per_triangle();
    assert!(
        ours < binary,
        "{ours:.1} vs binary {binary:.1} bytes per triangle"
    );
    let _: Hit = bvhtrace_cpu::trace_ray(&bvh, &Ray::new(Vec3::Z * 5.0, -Vec3::Z), Query::Any);
}

/// Rays from beside triangles in the planes `x = 3^(i - 40)` (`common::planes_at_origins`):
/// f32 rounds the distance of a plane at or behind the origin to a small positive `t`,
/// where the binary walk has missed that triangle's leaf box. The layout tests the leaf
/// boxes of such hits (`LeafBoxes`), and gives the full stack's hits to the bit, not
/// merely within the f32 exception.
#[test]
fn hits_at_the_origin_are_judged_by_their_leaf_boxes() {
    let (flat, rays) = common::planes_at_origins();
    let bvh = CpuBvh::from_flat(&flat).unwrap();
    assert!(
        bvh.kept_leaf_boxes() == 0,
        "one-triangle leaves: corner boxes"
    );
    let want = reference(&flat, &rays, Query::Closest);
    let got = every_isa(&bvh, &rays, Query::Closest);
    common::assert_same_hits(&rays, &got, &want);
    let any = every_isa(&bvh, &rays, Query::Any);
    let want_any = reference(&flat, &rays, Query::Any);
    for i in 0..rays.len() {
        assert_eq!(
            any[i].is_hit(),
            want_any[i].is_hit(),
            "any-hit ray {:?}",
            rays[i]
        );
    }
}

#[test]
fn one_scratch_serves_rays_of_trees_small_and_deep() {
    // A stack kept for a shallow tree grows for a deep one, and a deep tree's stack serves a
    // shallow one: every answer is trace_ray's, whichever came first.
    let small = common::uv_sphere(4, 1.0, Vec3::ZERO);
    let large = common::uv_sphere(96, 1.0, Vec3::new(0.5, 0.0, 0.0));
    let trees: Vec<(FlatBvh, CpuBvh, Vec<Ray>)> =
        [small, large, common::uv_sphere(4, 1.0, Vec3::ZERO)]
            .iter()
            .enumerate()
            .map(|(k, tris)| {
                let flat = FlatBvh::build(tris, &BuildOptions::default()).unwrap();
                let bvh = CpuBvh::from_flat(&flat).unwrap();
                (flat, bvh, common::rays_for(tris, 7 + k as u64, 300))
            })
            .collect();
    assert!(
        trees[1].1.depth() > trees[0].1.depth(),
        "the second tree must be deeper"
    );
    let mut scratch = bvhtrace_cpu::RayScratch::default();
    for (_, bvh, rays) in &trees {
        for q in [Query::Closest, Query::Any] {
            for ray in rays {
                let want = bvhtrace_cpu::trace_ray(bvh, ray, q);
                let got = bvhtrace_cpu::trace_ray_in(bvh, ray, q, &mut scratch);
                assert!(same(&got, &want), "{ray:?}: {got:?} vs {want:?}");
            }
        }
    }
}
