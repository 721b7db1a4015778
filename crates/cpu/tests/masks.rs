//! Alpha-masked trees (`FlatBvh::masks`): the layout's walks cut candidates as the core
//! walks do (`MaskTables::accept`, for candidates that beat the best), one level and two,
//! closest hits to the bit, any hits on hit or miss, every instruction set equal.

mod common;

use std::sync::Arc;

use bvhtrace_core::alpha::Wrap;
use bvhtrace_core::masks::{
    MASK_OPAQUE, MASK_TRANSPARENT, MICRO_CELLS, MICRO_WORDS, MaskMaterial, MaskTables,
    MaskTriangle, NO_MASKS,
};
use bvhtrace_core::{
    BuildOptions, FlatBvh, Hit, Instance, InstancedBvh, Query, Ray, TraceOptions, Traversal,
    Triangle, oracle,
};
use bvhtrace_cpu::{CpuBvh, Isa};
use common::{rays_for, same, triangle, xorshift};
use glam::{Affine3A, Quat, Vec3};
use proptest::prelude::*;

/// The full stack's hits.
fn reference(flat: &FlatBvh, rays: &[Ray], q: Query) -> Vec<Hit> {
    bvhtrace_core::trace_rays(flat, rays, &TraceOptions::new(Traversal::FullStack, q)).hits
}

/// Where the core walks' f32 exception may apply to a ray's two closest hits.
type Departure<'a> = &'a dyn Fn(&Ray, &Hit, &Hit) -> bool;

/// The layout's answers on every instruction set (equal to the bit) against the full
/// stack's: closest hits to the bit (or where `departure` allows, the f32 exception), any
/// hits on hit or miss as the closest hits. Returns the closest hits.
fn check(label: &str, flat: &FlatBvh, rays: &[Ray], departure: Departure<'_>) -> Vec<Hit> {
    let bvh = CpuBvh::from_flat(flat).expect("converts");
    assert!(bvh.masks().is_some(), "{label}: the masks came along");
    let mut closest = Vec::new();
    for q in [Query::Closest, Query::Any] {
        // Any hits are judged against the closest hits judged before them: where those
        // took the f32 exception (a triangle f32 cannot judge, hit by one walk and missed
        // by the other), the any hits take it too.
        let want = match q {
            Query::Closest => reference(flat, rays, q),
            Query::Any => closest.clone(),
        };
        let isas = Isa::all_available();
        let first = bvhtrace_cpu::trace_rays_with(&bvh, rays, q, isas[0]);
        for &isa in &isas[1..] {
            let h = bvhtrace_cpu::trace_rays_with(&bvh, rays, q, isa);
            for (i, (a, b)) in first.iter().zip(&h).enumerate() {
                assert!(
                    same(a, b),
                    "{label}: {isa} differs on ray {i}: {b:?} vs {a:?}"
                );
            }
        }
        for (i, (g, w)) in first.iter().zip(&want).enumerate() {
            let ok = match q {
                Query::Closest => same(g, w) || departure(&rays[i], g, w),
                Query::Any => g.is_hit() == w.is_hit() && (g.is_hit() || same(g, w)),
            };
            assert!(
                ok,
                "{label} {q:?}, ray {i} {:?}: got {g:?}, want {w:?}",
                rays[i]
            );
        }
        if q == Query::Closest {
            closest = first;
        }
    }
    closest
}

/// Rays straight down through the tree's box on a grid, and rays aimed at its triangles.
fn grid_rays(flat: &FlatBvh, tris: &[Triangle], seed: u64) -> Vec<Ray> {
    let b = flat.bounds();
    let mut rays = Vec::new();
    for j in 0..96 {
        for i in 0..128 {
            let x = b.min.x + (b.max.x - b.min.x) * (i as f32 + 0.5) / 128.0;
            let z = b.min.z + (b.max.z - b.min.z) * (j as f32 + 0.5) / 96.0;
            rays.push(Ray::new(Vec3::new(x, b.max.y + 1.0, z), Vec3::NEG_Y));
        }
    }
    rays.extend(rays_for(tris, seed, 6000));
    rays
}

/// The foliage scene (leaf cards, a fence and a gate cut by textures, a mirrored
/// instance), flattened and in two levels: the full stack's answers with its masks, and
/// the masks cut (dropping them changes many hits).
#[test]
fn foliage_traces_as_the_core_walks_with_its_masks() {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../scenes/foliage.gltf");
    let scene = bvhtrace_scene::load(path).unwrap();
    let world = scene.flattened_triangles().unwrap();
    for flatten in [true, false] {
        let traced = scene
            .tracing_bvh(&BuildOptions::default(), flatten)
            .unwrap();
        let label = if flatten { "flattened" } else { "two levels" };
        assert_eq!(traced.is_two_level(), !flatten, "{label}");
        let flat = traced.bvh();
        let masks = flat
            .masks()
            .expect("the foliage scene has masked triangles")
            .clone();
        let mut rays = grid_rays(flat, &world, 0xf01a);
        rays.extend(scene.camera_or_frame(4.0 / 3.0).rays(160, 120));
        masks.reset_counts();
        let hits = check(label, flat, &rays, &|_, _, _| false);
        let (settled, sampled) = masks.counts();
        assert!(
            settled > 0 && sampled > 0,
            "{label}: {settled} settled, {sampled} sampled"
        );
        let mut opaque = flat.clone();
        opaque.set_masks(None).unwrap();
        let bvh = CpuBvh::from_flat(&opaque).unwrap();
        assert!(bvh.masks().is_none());
        let without = bvhtrace_cpu::trace_rays(&bvh, &rays, Query::Closest);
        let changed = hits
            .iter()
            .zip(&without)
            .filter(|(a, b)| a.prim != b.prim)
            .count();
        assert!(
            changed > rays.len() / 50,
            "{label}: the masks changed {changed} hits"
        );
    }
}

/// Mask tables over `n` primitives drawn from `seed`: opaque, transparent, or a textured
/// record (random texture coordinates, micromap and 4x4 texture, under each wrap mode).
fn random_tables(states: usize, seed: u64, instance_bases: Vec<u32>) -> MaskTables {
    let mut rnd = xorshift(seed | 1);
    let mut pick = |n: u32| ((rnd() * n as f32) as u32).min(n - 1);
    let mut triangles = Vec::new();
    let mut st = Vec::with_capacity(states);
    for _ in 0..states {
        st.push(match pick(4) {
            0 => MASK_OPAQUE,
            1 => MASK_TRANSPARENT,
            _ => {
                let mut t = MaskTriangle {
                    uv: std::array::from_fn(|_| pick(700) as f32 / 100.0 - 3.0),
                    material: pick(2),
                    micro: [0; MICRO_WORDS],
                };
                for slot in 0..(2 * MICRO_CELLS * MICRO_CELLS) as usize {
                    t.set_micro_state(slot, pick(3));
                }
                triangles.push(t);
                triangles.len() as u32 - 1
            }
        });
    }
    let texels: Vec<u8> = (0..32).map(|_| pick(256) as u8).collect();
    let wraps = [Wrap::Repeat, Wrap::ClampToEdge, Wrap::MirroredRepeat];
    let materials = (0..2)
        .map(|m| MaskMaterial {
            first_texel: 16 * m,
            width: 4,
            height: 4,
            wrap: MaskMaterial::pack_wrap([wraps[pick(3) as usize], wraps[pick(3) as usize]]),
            min_texel: pick(256),
        })
        .collect();
    MaskTables::new(st, triangles, materials, texels, instance_bases).expect("valid tables")
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    /// A random masked soup (duplicates, slivers, huge offsets): the full stack's
    /// answers, every builder's leaf size.
    #[test]
    fn masked_soups_give_the_reference_hits(
        tris in common::soup(),
        leaf in prop::sample::select(vec![1usize, 4, 8]),
        seed in 1u64..u64::MAX,
    ) {
        let opts = BuildOptions { max_leaf_size: leaf, ..BuildOptions::default() };
        let mut flat = FlatBvh::build(&tris, &opts).unwrap();
        flat.set_masks(Some(Arc::new(random_tables(tris.len(), seed, vec![])))).unwrap();
        let rays = rays_for(&tris, seed, 400);
        check("soup", &flat, &rays, &|r, a, b| common::f32_departure(&tris, r, a, b));
    }

    /// Random masked meshes placed by instances (mirrored, scaled, turned), each mesh's
    /// states at its own base, some instances without masks: the full stack's answers.
    #[test]
    fn masked_instances_give_the_reference_hits(
        meshes in prop::collection::vec(prop::collection::vec(triangle(), 1..40), 1..4),
        placements in prop::collection::vec(
            (0u32..3, -3.0f32..3.0, prop::bool::ANY, -10.0f32..10.0, 0u32..4), 1..10),
        seed in 1u64..u64::MAX,
    ) {
        let instances: Vec<Instance> = placements
            .iter()
            .map(|&(m, turn, mirror, x, _)| {
                let s = if mirror { Vec3::new(-1.0, 1.0, 1.0) } else { Vec3::ONE };
                let rot = Quat::from_axis_angle(Vec3::new(0.3, 1.0, 0.2).normalize(), turn);
                let t = Affine3A::from_scale_rotation_translation(s, rot, Vec3::new(x, 0.0, -x));
                Instance::new(m % meshes.len() as u32, t)
            })
            .collect();
        let Ok(mut ib) = InstancedBvh::build(&meshes, instances.clone(), &BuildOptions::default()) else {
            return Ok(());
        };
        // Each mesh's states one after the other; an instance with `k == 0` has none.
        let mut starts = vec![0u32];
        for m in &meshes {
            starts.push(starts.last().unwrap() + m.len() as u32);
        }
        let bases = instances
            .iter()
            .zip(&placements)
            .map(|(i, p)| if p.4 == 0 { NO_MASKS } else { starts[i.mesh as usize] })
            .collect();
        let tables = random_tables(*starts.last().unwrap() as usize, seed, bases);
        ib.set_masks(Some(Arc::new(tables))).unwrap();
        let world: Vec<Triangle> = instances
            .iter()
            .flat_map(|i| meshes[i.mesh as usize].iter().map(move |t| t.map(|p| i.transform.transform_point3(p))))
            .collect();
        let rays = rays_for(&world, seed, 400);
        // The exception arises in the mesh's space, for the ray its triangle is tested with.
        let object = |p: u32| {
            let (i, local) = ib.locate(p)?;
            let mesh = &meshes[instances[i as usize].mesh as usize];
            Some((mesh[local as usize], i))
        };
        let departure = |r: &Ray, a: &Hit, b: &Hit| {
            let at = |h: &Hit| {
                object(h.prim).map(|(t, i)| (t, ib.bvh().instances()[i as usize].ray_to_object(r)))
            };
            let terr = |h: &Hit| at(h).map_or(0.0, |(t, o)| oracle::f32_t_error_bound(&t, &o));
            [a, b].iter().any(|h| at(h).is_some_and(|(t, o)| oracle::f32_indeterminate(&t, &o)))
                || (a.t as f64 - b.t as f64).abs() <= terr(a) + terr(b)
        };
        check("instances", ib.bvh(), &rays, &departure);
    }
}
