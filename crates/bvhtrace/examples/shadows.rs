//! A program of your own on the front door: a box on a floor, seen from above, lit by a
//! point light, drawn as text. Camera rays find the closest hit, shadow rays any hit,
//! on the backend named on the command line, and the CPU walks check every answer.
//!
//! ```text
//! cargo run --release -p bvhtrace --example shadows -- [auto|cpu|wgpu|vulkan]
//! ```

use bvhtrace::core::{Hit, Triangle};
use bvhtrace::glam::Vec3;
use bvhtrace::{Backend, BuildOptions, FlatBvh, OpenOptions, Ray, TraceOptions};

/// The two triangles of the quad `a b c d` (counter-clockwise).
fn quad(a: Vec3, b: Vec3, c: Vec3, d: Vec3) -> [Triangle; 2] {
    [[a, b, c], [a, c, d]]
}

/// A floor 8 wide and a unit box standing on it.
fn scene() -> Vec<Triangle> {
    let v = |x, y, z| Vec3::new(x, y, z);
    let mut tris = quad(
        v(-4., 0., -4.),
        v(-4., 0., 4.),
        v(4., 0., 4.),
        v(4., 0., -4.),
    )
    .to_vec();
    let corner = |i: u32| v((i & 1) as f32, ((i >> 1) & 1) as f32 * 1.5, (i >> 2) as f32);
    for [a, b, c, d] in [
        [0, 1, 3, 2],
        [4, 6, 7, 5],
        [0, 4, 5, 1],
        [2, 3, 7, 6],
        [0, 2, 6, 4],
        [1, 5, 7, 3],
    ] {
        tris.extend(quad(corner(a), corner(b), corner(c), corner(d)));
    }
    tris
}

fn main() {
    if let Err(e) = run() {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let backend: Backend = std::env::args()
        .nth(1)
        .as_deref()
        .unwrap_or("auto")
        .parse()?;
    let tris = scene();
    let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
    let opened = bvhtrace::open(&bvh, &OpenOptions::new(backend))?;
    let cpu = bvhtrace::open(&bvh, &OpenOptions::new(Backend::Cpu))?;
    println!("{}", opened.summary());
    if let Some(why) = &opened.fallback {
        println!("note: {why}");
    }
    // 64 x 32 camera rays looking down at the floor from above and to the side.
    let (w, h, eye) = (64, 32, Vec3::new(0.5, 9.0, 7.0));
    let rays: Vec<Ray> = (0..w * h)
        .map(|i| {
            let (x, y) = (
                (i % w) as f32 / w as f32 - 0.5,
                (i / w) as f32 / h as f32 - 0.5,
            );
            let target = Vec3::new(7.6 * x, 0.0, 7.6 * y);
            Ray::new(eye, (target - eye).normalize())
        })
        .collect();
    let walk = opened.traversal;
    let seen = opened.tracer.trace(&rays, &TraceOptions::closest(walk))?;
    let light = Vec3::new(-3.0, 6.0, -2.0);
    // A shadow ray from each visible point toward the light: any hit is enough.
    let shadow: Vec<Ray> = (rays.iter().zip(&seen.hits))
        .filter(|(_, hit)| hit.is_hit())
        .map(|(ray, hit)| {
            hit.surface(&tris[hit.prim as usize], Vec3::from(ray.dir))
                .ray_toward(light)
        })
        .collect();
    let blocked = opened.tracer.trace(&shadow, &TraceOptions::any(walk))?;
    for (what, rays, out, opts) in [
        ("camera", &rays, &seen, TraceOptions::closest(walk)),
        ("shadow", &shadow, &blocked, TraceOptions::any(walk)),
    ] {
        let reference = cpu.tracer.trace(rays, &opts)?;
        let same = |a: &Hit, b: &Hit| a.prim == b.prim && (!a.is_hit() || a.t == b.t);
        let differ = (out.hits.iter().zip(&reference.hits)).filter(|(a, b)| !same(a, b));
        println!(
            "{what} rays: {}, answers unlike the CPU's: {}",
            rays.len(),
            differ.count()
        );
    }
    let mut shadows = blocked.hits.iter();
    for row in seen.hits.chunks(w) {
        let line: String = (row.iter())
            .map(|hit| {
                match (
                    hit.is_hit(),
                    hit.is_hit() && shadows.next().is_some_and(Hit::is_hit),
                ) {
                    (false, _) => ' ',
                    (true, true) => '#',
                    (true, false) if hit.prim < 2 => '.',
                    _ => 'o',
                }
            })
            .collect();
        println!("{line}");
    }
    Ok(())
}
