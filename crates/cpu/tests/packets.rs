//! The packet walk against the single-ray walk: closest hits equal to the bit (primitive,
//! `t`, `u`, `v`), any hits equal on hit or miss, on every instruction set; rays
//! incoherent within a packet, with `t_min > 0` or `< 0`, along slabs, invalid, and
//! packets cut short.

use bvhtrace_core::{BuildOptions, BuilderKind, FlatBvh, Query, Ray};
use bvhtrace_cpu::{CpuBvh, Isa, PACKET};
use glam::Vec3;
use proptest::prelude::*;

mod common;
use common::{reference, same};

/// Checks `trace_packets` against `trace_rays` on every instruction set: closest hits
/// equal to the bit, or (with `tris`) the documented f32 departure, where the two walks'
/// different visit orders may rightly keep either of two triangles f32 cannot order.
/// Returns the single-ray closest hits.
fn check(
    bvh: &CpuBvh,
    rays: &[Ray],
    tris: Option<&[bvhtrace_core::Triangle]>,
) -> Result<Vec<bvhtrace_core::Hit>, TestCaseError> {
    let single = bvhtrace_cpu::trace_rays(bvh, rays, Query::Closest);
    let single_any = bvhtrace_cpu::trace_rays(bvh, rays, Query::Any);
    for isa in Isa::all_available() {
        let got = bvhtrace_cpu::trace_packets_with(bvh, rays, Query::Closest, isa);
        let any = bvhtrace_cpu::trace_packets_with(bvh, rays, Query::Any, isa);
        for (i, ray) in rays.iter().enumerate() {
            let (g, w) = (&got[i], &single[i]);
            let departs = tris.is_some_and(|t| common::f32_departure(t, ray, g, w));
            prop_assert!(
                same(g, w) || departs,
                "{isa} ray {i} {ray:?}: {g:?} vs single {w:?}"
            );
            let (a, wa) = (&any[i], &single_any[i]);
            prop_assert_eq!(
                a.is_hit(),
                wa.is_hit(),
                "{} any-hit ray {} {:?}",
                isa,
                i,
                ray
            );
            if a.is_hit() {
                prop_assert!(a.t >= ray.t_min && a.t < ray.t_max);
            } else {
                prop_assert!(same(a, wa), "{isa} any-hit miss {a:?} vs {wa:?}");
            }
        }
    }
    Ok(single)
}

/// `rays` with some made untraceable, some given an interval starting after the origin,
/// and some empty.
fn spoil(mut rays: Vec<Ray>, seed: u64) -> Vec<Ray> {
    let mut rnd = common::xorshift(seed | 1);
    for (i, r) in rays.iter_mut().enumerate() {
        match i % 13 {
            2 => r.origin[1] = f32::NAN,
            4 => r.dir = [0.0; 3],
            8 => r.t_min = rnd() * 3.0,
            10 => (r.t_min, r.t_max) = (2.0, 1.0),
            11 => r.t_max = f32::NAN,
            _ => {}
        }
    }
    rays
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(96))]

    #[test]
    fn packets_give_the_single_ray_hits(
        tris in common::soup(),
        seed in any::<u64>(),
        b in 0usize..BuilderKind::ALL.len(),
        leaf in prop::sample::select(vec![1usize, 3, 8, 80]),
        n in 1usize..(3 * PACKET),
    ) {
        let opts = BuildOptions { max_leaf_size: leaf, ..BuildOptions::with_builder(BuilderKind::ALL[b]) };
        let flat = FlatBvh::build(&tris, &opts).unwrap();
        let bvh = CpuBvh::from_flat(&flat).unwrap();
        check(&bvh, &spoil(common::rays_for(&tris, seed, n), seed), Some(&tris))?;
    }
}

/// Coherent packets (a pinhole camera's 8x8 tiles) over closed spheres, with the eye
/// inside and outside, and a packet where every ray goes its own way.
#[test]
fn coherent_and_scattered_packets_on_spheres() {
    let tris = common::uv_sphere(24, 1.0, Vec3::new(0.1, -0.2, 0.3));
    let flat = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
    let bvh = CpuBvh::from_flat(&flat).unwrap();
    for eye in [Vec3::new(0.2, 0.1, -3.0), Vec3::new(0.0, 0.0, 0.2)] {
        let (w, h) = (40u32, 24u32);
        let mut rays = Vec::new();
        for &p in &bvhtrace_cpu::tile_order(w, h) {
            let (x, y) = (
                (p % w) as f32 / w as f32 - 0.5,
                (p / w) as f32 / h as f32 - 0.5,
            );
            rays.push(Ray::new(eye, Vec3::new(x * 1.2, y, 1.0)));
        }
        let hits = check(&bvh, &rays, None).unwrap();
        let want = reference(&flat, &rays, Query::Closest);
        assert!(hits.iter().zip(&want).all(|(g, w)| same(g, w)));
        assert!(hits.iter().filter(|h| h.is_hit()).count() > rays.len() / 4);
    }
    let mut rnd = common::xorshift(7);
    let scattered: Vec<Ray> = (0..PACKET)
        .map(|_| {
            let d = Vec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5);
            Ray::new(Vec3::new(rnd(), rnd(), rnd()) * 4.0 - 2.0, d)
        })
        .collect();
    check(&bvh, &scattered, None).unwrap();
}

/// `tile_order` is a permutation of the pixels, one 8x8 tile per packet.
/// Hits at or behind the rays' origins (`common::planes_at_origins`), where only the leaf
/// boxes decide as the binary walk does: packets of those rays (64 at a time, both
/// triangle tests: rays sharing their axes in lanes, the others one by one), closest hits
/// the full stack's to the bit, any hits its verdicts.
#[test]
fn packets_judge_hits_at_the_origin_by_their_leaf_boxes() {
    let (flat, mut rays) = common::planes_at_origins();
    // Coherent groups too: runs of rays from one origin, so that lanes share their axes.
    let extra: Vec<Ray> = rays
        .iter()
        .step_by(8)
        .flat_map(|r| {
            (0..8).map(move |k| {
                Ray::new(
                    Vec3::from(r.origin),
                    Vec3::from(r.dir) + Vec3::splat(k as f32 * 1e-3),
                )
            })
        })
        .collect();
    rays.extend(extra);
    let bvh = CpuBvh::from_flat(&flat).unwrap();
    for isa in bvhtrace_cpu::Isa::all_available() {
        let got = bvhtrace_cpu::trace_packets_with(&bvh, &rays, Query::Closest, isa);
        common::assert_same_hits(
            &rays,
            &got,
            &common::reference(&flat, &rays, Query::Closest),
        );
        let any = bvhtrace_cpu::trace_packets_with(&bvh, &rays, Query::Any, isa);
        let want = common::reference(&flat, &rays, Query::Any);
        for i in 0..rays.len() {
            assert_eq!(
                any[i].is_hit(),
                want[i].is_hit(),
                "{isa} any-hit ray {:?}",
                rays[i]
            );
        }
    }
}

/// `coherent` takes camera rays (row-major or in tiles) and rays toward one point, and
/// refuses rays in random directions and batches shorter than a packet.
#[test]
fn coherence_is_told_from_the_directions() {
    let (w, h) = (64u32, 48u32);
    let camera: Vec<Ray> = (0..w * h)
        .map(|k| {
            let (x, y) = (
                (k % w) as f32 / w as f32 - 0.5,
                (k / w) as f32 / h as f32 - 0.5,
            );
            Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::new(x, y, -1.0))
        })
        .collect();
    assert!(bvhtrace_cpu::coherent(&camera));
    let tiled: Vec<Ray> = bvhtrace_cpu::tile_order(w, h)
        .iter()
        .map(|&i| camera[i as usize])
        .collect();
    assert!(bvhtrace_cpu::coherent(&tiled));
    let light = Vec3::new(3.0, 4.0, 5.0);
    let shadow: Vec<Ray> = camera
        .iter()
        .map(|r| {
            let p = Vec3::from(r.origin) + Vec3::from(r.dir) * 4.0;
            Ray::new(p, light - p)
        })
        .collect();
    assert!(bvhtrace_cpu::coherent(&shadow));
    let mut next = common::xorshift(7);
    let scattered: Vec<Ray> = (0..4096)
        .map(|_| {
            Ray::new(
                Vec3::ZERO,
                Vec3::new(next() - 0.5, next() - 0.5, next() - 0.5),
            )
        })
        .collect();
    assert!(!bvhtrace_cpu::coherent(&scattered));
    assert!(!bvhtrace_cpu::coherent(&camera[..63]));
}

#[test]
fn tile_order_is_a_permutation_in_tiles() {
    for (w, h) in [(16u32, 8u32), (20, 13), (1, 1), (64, 64)] {
        let order = bvhtrace_cpu::tile_order(w, h);
        let mut seen = vec![false; (w * h) as usize];
        for &p in &order {
            assert!(!seen[p as usize]);
            seen[p as usize] = true;
        }
        assert!(seen.iter().all(|&s| s));
    }
    let order = bvhtrace_cpu::tile_order(16, 8);
    assert!(order[..PACKET].iter().all(|&p| p % 16 < 8));
}

/// bunny_69k and igea: camera rays and shadow rays in 8x8 tiles, packets equal to single
/// rays and to the reference walk.
#[test]
fn real_meshes_in_tiles_give_the_single_ray_hits() {
    for name in ["bunny_69k", "igea"] {
        let Some((_, flat, primary, shadow)) = common::scene_rays(name, 320, 240) else {
            println!("{name}: skipped, no shared scenes folder");
            continue;
        };
        let bvh = CpuBvh::from_flat(&flat).unwrap();
        let order = bvhtrace_cpu::tile_order(320, 240);
        let tiled: Vec<Ray> = order.iter().map(|&p| primary[p as usize]).collect();
        let hits = check(&bvh, &tiled, None).unwrap();
        let want = reference(&flat, &tiled, Query::Closest);
        let differ = hits.iter().zip(&want).filter(|(g, w)| !same(g, w)).count();
        assert_eq!(differ, 0, "{name}: primary rays differ from the reference");
        check(&bvh, &shadow, None).unwrap();
    }
}
