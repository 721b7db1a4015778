//! Quick speed figures for the CPU layout against the core walks, on the shared scenes:
//! `cargo run --release -p bvhtrace-cpu --example speed -- [W H RUNS]`.
//! The CLI's `bench-trace --cpu-only` is the full comparison (with Embree).

use std::time::Instant;

use bvhtrace_core::{Query, Ray, TraceOptions, Traversal};
use bvhtrace_cpu::{CpuBvh, Isa};

#[path = "../tests/common.rs"]
mod common;

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn time(runs: usize, mut f: impl FnMut()) -> f64 {
    f();
    median(
        (0..runs)
            .map(|_| {
                let t = Instant::now();
                f();
                t.elapsed().as_secs_f64() * 1e3
            })
            .collect(),
    )
}

/// One cosine-weighted bounce from each primary hit, as `bench-trace` makes them (the
/// core's `cosine_dir`, seeded by the pixel).
fn diffuse_rays(
    tris: &[bvhtrace_core::Triangle],
    flat: &bvhtrace_core::FlatBvh,
    primary: &[Ray],
) -> Vec<Ray> {
    let hits = common::reference(flat, primary, Query::Closest);
    (primary.iter().zip(&hits).enumerate())
        .filter(|(_, (_, h))| h.is_hit())
        .map(|(i, (r, h))| {
            let p = h.surface(&tris[h.prim as usize], glam::Vec3::from(r.dir));
            let dir = bvhtrace_core::surface::cosine_dir(p.normal, i as u32, 0);
            p.spawn_ray(dir, f32::INFINITY)
        })
        .collect()
}

/// The shadow rays of each 8x8 tile as one packet, as `bench-trace` puts them
/// ([`bvhtrace_cpu::Tiles::packets`]); `shadow` holds one per hit pixel, in pixel order.
fn shadow_tiles(
    flat: &bvhtrace_core::FlatBvh,
    primary: &[Ray],
    shadow: &[Ray],
    (w, h): (u32, u32),
) -> Vec<Ray> {
    let hits = common::reference(flat, primary, Query::Closest);
    let owner: Vec<u32> = (0..hits.len() as u32)
        .filter(|&p| hits[p as usize].is_hit())
        .collect();
    bvhtrace_cpu::Tiles::new(w, h).packets(shadow, &owner).0
}

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .filter_map(|a| a.parse().ok())
        .collect();
    let (w, h, runs) = (
        *args.first().unwrap_or(&1024) as u32,
        *args.get(1).unwrap_or(&768) as u32,
        *args.get(2).unwrap_or(&5),
    );
    let only = |var: &str, v: &str| std::env::var(var).is_ok_and(|s| s != v);
    for name in ["bunny_69k", "igea"] {
        if only("SPEED_SCENE", name) {
            continue;
        }
        let Some((tris, mut flat, primary, shadow)) = common::scene_rays(name, w, h) else {
            eprintln!("no shared scenes");
            return;
        };
        flat.build_wide();
        let t = Instant::now();
        let bvh = CpuBvh::from_flat(&flat).unwrap();
        let convert = t.elapsed().as_secs_f64() * 1e3;
        let (bn, _) = bvh.byte_sizes();
        println!(
            "{name}: {} tris, convert {convert:.1} ms, {} nodes, {} blocks, {:.1} bytes/tri, depth {}",
            tris.len(),
            bn / 256,
            bvh.blocks().len(),
            bvh.bytes_per_triangle(),
            bvh.depth()
        );
        let diffuse = diffuse_rays(&tris, &flat, &primary);
        for (kind, rays, q) in [
            ("primary", &primary, Query::Closest),
            ("shadow", &shadow, Query::Any),
            ("diffuse", &diffuse, Query::Closest),
            ("diffany", &diffuse, Query::Any),
        ] {
            if only("SPEED_KIND", kind) {
                continue;
            }
            if let Ok(path) = std::env::var("SPEED_DUMP") {
                // The `BVHD` dump `embree_trace` reads (crates/cli/src/embree.rs).
                let mut b = b"BVHD".to_vec();
                for v in [1u32, tris.len() as u32, rays.len() as u32] {
                    b.extend_from_slice(&v.to_le_bytes());
                }
                let floats =
                    tris.iter()
                        .flatten()
                        .flat_map(|p| p.to_array())
                        .chain(rays.iter().flat_map(|r| {
                            [
                                r.origin[0],
                                r.origin[1],
                                r.origin[2],
                                r.t_min,
                                r.dir[0],
                                r.dir[1],
                                r.dir[2],
                                r.t_max,
                            ]
                        }));
                for f in floats {
                    b.extend_from_slice(&f.to_le_bytes());
                }
                std::fs::write(&path, b).expect("dump written");
            }
            let n = rays.len() as f64;
            let mr = |ms: f64| n / ms / 1e3;
            let walks = if std::env::var_os("SPEED_CPU_ONLY").is_some() {
                vec![]
            } else {
                vec![Traversal::FullStack, Traversal::Wide]
            };
            for tr in walks {
                let o = TraceOptions::new(tr, q);
                let ms = time(runs, || {
                    std::hint::black_box(bvhtrace_core::trace_rays(&flat, rays, &o));
                });
                println!("  {kind:8} core {tr:12} {:7.2} Mrays/s", mr(ms));
            }
            for isa in Isa::all_available()
                .into_iter()
                .filter(|i| std::env::var_os("SPEED_CPU_ONLY").is_none() || *i == Isa::Avx2)
            {
                let ms = time(runs, || {
                    std::hint::black_box(bvhtrace_cpu::trace_rays_with(&bvh, rays, q, isa));
                });
                let hits = bvhtrace_cpu::trace_rays_with(&bvh, rays, q, isa);
                let n_hit = hits.iter().filter(|h| h.is_hit()).count();
                println!(
                    "  {kind:8} cpu  {isa:12} {:7.2} Mrays/s ({n_hit} hits)",
                    mr(ms)
                );
            }
            // Packets of 64 consecutive rays: in the rays' own (row-major) order, and
            // camera rays and their shadow rays put in 8x8 tiles.
            let tiled: Vec<Ray> = match kind {
                "primary" => bvhtrace_cpu::tile_order(w, h)
                    .iter()
                    .map(|&i| rays[i as usize])
                    .collect(),
                "shadow" => shadow_tiles(&flat, &primary, rays, (w, h)),
                _ => Vec::new(),
            };
            for (order, rs) in [("rows", rays.as_slice()), ("tiles", tiled.as_slice())] {
                if rs.is_empty() || only("SPEED_ORDER", order) {
                    continue;
                }
                let ms = time(runs, || {
                    std::hint::black_box(bvhtrace_cpu::trace_packets(&bvh, rs, q));
                });
                println!("  {kind:8} cpu  packets {order:5} {:7.2} Mrays/s", mr(ms));
            }
        }
    }
}
