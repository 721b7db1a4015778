//! Embree 3 beside us on the same triangles and rays: the `BVHD` dump that
//! `crates/cli/embree/embree_trace.c` reads, and running that program.

use std::path::Path;

use anyhow::{Context, Result, bail};
use bvhtrace_core::motion::{MotionMesh, MovingInstance};
use bvhtrace_core::{CurveKind, Curves, Ray, Triangle};

/// The dump format: "BVHD", u32 version 1, u32 triangle count, u32 ray count, 9 f32 per
/// triangle, 8 f32 per ray (origin, t_min, dir, t_max), little endian.
pub fn dump_bytes(tris: &[Triangle], rays: &[Ray]) -> Vec<u8> {
    let mut bytes = Vec::with_capacity(16 + tris.len() * 36 + rays.len() * 32);
    bytes.extend_from_slice(b"BVHD");
    for v in [1u32, tris.len() as u32, rays.len() as u32] {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    put_triangles(&mut bytes, tris);
    put_rays(&mut bytes, rays);
    bytes
}

/// Version 2, a moving mesh: "BVHD", u32 version 2, u32 triangle count, u32 ray count, u32
/// time steps, the 9 f32 of every triangle at step 0, then at step 1, ..., the rays as in
/// version 1, then one f32 time in `[0, 1]` per ray, little endian.
pub fn motion_dump_bytes(mesh: &MotionMesh, rays: &[Ray], times: &[f32]) -> Vec<u8> {
    let steps = mesh.time_steps();
    let mut bytes = Vec::with_capacity(20 + steps * mesh.len() * 36 + rays.len() * 36);
    bytes.extend_from_slice(b"BVHD");
    for v in [2, mesh.len(), rays.len(), steps] {
        bytes.extend_from_slice(&(v as u32).to_le_bytes());
    }
    for k in 0..steps {
        put_triangles(&mut bytes, mesh.step(k));
    }
    put_rays(&mut bytes, rays);
    for t in times {
        bytes.extend_from_slice(&t.to_le_bytes());
    }
    bytes
}

/// Version 3, meshes under moving instances: "BVHD", u32 version 3, u32 mesh count, u32 ray
/// count, u32 instance count, u32 time steps; each mesh as a u32 triangle count and 9 f32
/// per triangle; each instance as a u32 mesh, a u32 transform count (1 or the steps) and
/// 12 f32 per transform (3x4, column major); the rays as in version 1; one f32 time per ray.
pub fn instanced_dump_bytes(
    meshes: &[Vec<Triangle>],
    instances: &[MovingInstance],
    rays: &[Ray],
    times: &[f32],
) -> Vec<u8> {
    let steps = instances
        .iter()
        .map(|i| i.transforms.len())
        .max()
        .unwrap_or(1)
        .max(2);
    let mut bytes = Vec::new();
    bytes.extend_from_slice(b"BVHD");
    for v in [3, meshes.len(), rays.len(), instances.len(), steps] {
        bytes.extend_from_slice(&(v as u32).to_le_bytes());
    }
    for m in meshes {
        bytes.extend_from_slice(&(m.len() as u32).to_le_bytes());
        put_triangles(&mut bytes, m);
    }
    for inst in instances {
        for v in [inst.mesh, inst.transforms.len()] {
            bytes.extend_from_slice(&(v as u32).to_le_bytes());
        }
        for m in &inst.transforms {
            // The 3x4 column-major matrix Embree takes: the upper three rows of each column.
            for c in m.to_cols_array_2d() {
                for x in &c[..3] {
                    bytes.extend_from_slice(&x.to_le_bytes());
                }
            }
        }
    }
    put_rays(&mut bytes, rays);
    for t in times {
        bytes.extend_from_slice(&t.to_le_bytes());
    }
    bytes
}

/// Version 4, triangles and curves: "BVHD", u32 version 4, u32 triangle count, u32 ray
/// count, u32 curve kind (0 round linear, 1 flat linear, 2 round Bezier, 3 round B-spline:
/// [`CurveKind::ALL`]'s order), u32 point count, u32 segment count; 9 f32 per triangle, 4
/// f32 per point (xyz, radius), a u32 first point per segment, a u8 of Embree's neighbour
/// flags per segment (1 left, 2 right; linear kinds), the rays as in version 1. A curve's
/// primitive id is the triangle count plus its segment.
pub fn curve_dump_bytes(tris: &[Triangle], curves: &Curves, rays: &[Ray]) -> Vec<u8> {
    let mut bytes = Vec::new();
    bytes.extend_from_slice(b"BVHD");
    let kind = CurveKind::ALL.iter().position(|&k| k == curves.kind);
    let (n_points, n_segments) = (curves.points.len(), curves.len());
    for v in [
        4,
        tris.len(),
        rays.len(),
        kind.unwrap_or(0),
        n_points,
        n_segments,
    ] {
        bytes.extend_from_slice(&(v as u32).to_le_bytes());
    }
    put_triangles(&mut bytes, tris);
    for c in curves.points.iter().flat_map(|p| p.to_array()) {
        bytes.extend_from_slice(&c.to_le_bytes());
    }
    for s in &curves.segments {
        bytes.extend_from_slice(&s.to_le_bytes());
    }
    bytes.extend((0..n_segments).map(|s| {
        let (left, right) = curves.neighbours(s);
        u8::from(left) | (u8::from(right) << 1)
    }));
    put_rays(&mut bytes, rays);
    bytes
}

fn put_triangles(bytes: &mut Vec<u8>, tris: &[Triangle]) {
    for p in tris.iter().flatten() {
        for c in p.to_array() {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
}

fn put_rays(bytes: &mut Vec<u8>, rays: &[Ray]) {
    for r in rays {
        for c in r
            .origin
            .iter()
            .chain([&r.t_min])
            .chain(&r.dir)
            .chain([&r.t_max])
        {
            bytes.extend_from_slice(&c.to_le_bytes());
        }
    }
}

/// A dump written to a temporary file, removed when dropped.
pub struct Dump(std::path::PathBuf);

impl Dump {
    /// Writes `tris` and `rays` to a temporary file named after `tag`.
    pub fn write(tag: &str, tris: &[Triangle], rays: &[Ray]) -> Result<Dump> {
        let path = std::env::temp_dir().join(format!("bvhtrace-{tag}-{}.bin", std::process::id()));
        std::fs::write(&path, dump_bytes(tris, rays))
            .with_context(|| format!("writing {}", path.display()))?;
        Ok(Dump(path))
    }

    /// Runs `exe` (an `embree_trace` binary) on the dump with `threads` threads and `runs`
    /// runs, with `env` set; returns the JSON object it prints.
    pub fn run(
        &self,
        exe: &Path,
        threads: usize,
        runs: usize,
        env: &[(&str, String)],
    ) -> Result<serde_json::Value> {
        let out = std::process::Command::new(exe)
            .arg(&self.0)
            .args([threads.to_string(), runs.to_string()])
            .envs(env.iter().map(|(k, v)| (*k, v.as_str())))
            .output()
            .with_context(|| format!("running {}", exe.display()))?;
        if !out.status.success() {
            bail!(
                "{} failed: {}",
                exe.display(),
                String::from_utf8_lossy(&out.stderr)
            );
        }
        serde_json::from_slice(&out.stdout)
            .with_context(|| format!("{} printed no JSON", exe.display()))
    }
}

impl Drop for Dump {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

/// The Embree `embree_trace` ran, from its JSON's `tracer` (`embree 4.4.0 robust, medium
/// build`): `Embree 4.4.0`, or `Embree` when it does not say.
pub fn version(v: &serde_json::Value) -> String {
    let tracer = v["tracer"].as_str().unwrap_or_default();
    let mut words = tracer.split_whitespace().skip(1);
    match words.next() {
        Some(version) if tracer.starts_with("embree ") => format!("Embree {version}"),
        _ => "Embree".to_string(),
    }
}

/// Field `k` of `embree_trace`'s JSON as a number.
pub fn field(v: &serde_json::Value, k: &str, exe: &Path) -> Result<f64> {
    v[k].as_f64()
        .with_context(|| format!("no {k} from {}", exe.display()))
}

#[cfg(test)]
mod tests {
    use super::version;
    use serde_json::json;

    #[test]
    fn the_helpers_embree_is_named_by_its_version() {
        let four = json!({ "tracer": "embree 4.4.0 robust, medium build" });
        assert_eq!(version(&four), "Embree 4.4.0");
        let three = json!({ "tracer": "embree 3.13.5 fast, medium build" });
        assert_eq!(version(&three), "Embree 3.13.5");
        assert_eq!(version(&json!({})), "Embree");
    }
}
