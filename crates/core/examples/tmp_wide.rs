use bvhtrace_core::*;
use glam::Vec3;
use std::time::Instant;
fn main() {
    for path in std::env::args().skip(1) {
        let b = std::fs::read(&path).unwrap();
        let u = |o: usize| u32::from_le_bytes(b[o..o + 4].try_into().unwrap());
        let f = |o: usize| f32::from_le_bytes(b[o..o + 4].try_into().unwrap());
        let (nt, nr) = (u(8) as usize, u(12) as usize);
        let tris: Vec<Triangle> = (0..nt)
            .map(|i| {
                let o = 16 + i * 36;
                [
                    Vec3::new(f(o), f(o + 4), f(o + 8)),
                    Vec3::new(f(o + 12), f(o + 16), f(o + 20)),
                    Vec3::new(f(o + 24), f(o + 28), f(o + 32)),
                ]
            })
            .collect();
        let r0 = 16 + nt * 36;
        let rays: Vec<Ray> = (0..nr)
            .map(|i| {
                let o = r0 + i * 32;
                Ray::with_interval(
                    Vec3::new(f(o), f(o + 4), f(o + 8)),
                    Vec3::new(f(o + 16), f(o + 20), f(o + 24)),
                    f(o + 12),
                    f(o + 28),
                )
            })
            .collect();
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).unwrap();
        let t = Instant::now();
        let bvh = bvh.with_wide();
        let w = bvh.wide.as_ref().unwrap();
        println!(
            "{path}: collapse {:.1} ms, wide nodes {}, depth {}",
            t.elapsed().as_secs_f64() * 1e3,
            w.nodes.len(),
            w.depth
        );
        let first = trace_rays(&bvh, &rays, &TraceOptions::closest(Traversal::FullStack)).hits;
        let sel = std::env::var("SEL").unwrap_or_default();
        let rays: Vec<Ray> = rays
            .iter()
            .zip(&first)
            .filter(|(_, h)| match sel.as_str() {
                "hit" => h.is_hit(),
                "miss" => !h.is_hit(),
                _ => true,
            })
            .map(|(r, _)| *r)
            .collect();
        for tv in [Traversal::FullStack, Traversal::Wide]
            .into_iter()
            .filter(|t| std::env::var("ONLY").map_or(true, |o| o == t.name()))
        {
            let opts = TraceOptions::closest(tv);
            let c = trace_rays(&bvh, &rays, &opts.with_counters(true));
            let cs = c.counters.unwrap();
            let nodes: u64 = cs.iter().map(|c| c.nodes as u64).sum();
            let trs: u64 = cs.iter().map(|c| c.tris as u64).sum();
            let hits = c.hits.iter().filter(|h| h.is_hit()).count();
            let mut ms = vec![];
            for _ in 0..9 {
                let t = Instant::now();
                std::hint::black_box(trace_rays(&bvh, &rays, &opts));
                ms.push(t.elapsed().as_secs_f64() * 1e3);
            }
            ms.sort_by(f64::total_cmp);
            println!(
                "  {tv}: {:.2} Mrays/s, hits {hits}, nodes/ray {:.1} tris/ray {:.2}",
                rays.len() as f64 / ms[4] / 1e3,
                nodes as f64 / rays.len() as f64,
                trs as f64 / rays.len() as f64
            );
        }
    }
}
