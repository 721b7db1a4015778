//! The CPU twin of `shaders/path_trace.wgsl`: the same paths, traced by the CPU walks
//! (`bvhtrace_core::trace_ray_with`, which answer as the device's walks do), shaded with
//! [`crate::sampling`], summed in the same order. On a device that rounds as IEEE 754 says
//! (lavapipe) its sums equal the device's bit for bit.

use bvhtrace_core::hits::instance_surface;
use bvhtrace_core::surface::{SurfacePoint, offset_ray_origin};
use bvhtrace_core::{
    FlatBvh, Hit, INCOMPLETE, INVALID_RAY, InstancedBvh, MISS, Ray, TraceOptions, Traversal,
    Triangle,
};
use glam::Vec3;
use rayon::prelude::*;

use crate::material::{NO_TEXTURE, PathMaterial};
use crate::sampling::{Frame, PI, Rng, cross, dot, eval, luminance, mis, normalize, sample};
use crate::scene::{NO_LIGHT, PathParams, PathScene};
use crate::textures::textured;
use crate::{Accumulation, PathError, PathStats};

/// `PATH_FAR`.
const FAR: f32 = 1e30;

/// The CPU path tracer over one mesh's BVH or two levels: what the device traces, on the
/// CPU.
pub struct CpuPathTracer<'a> {
    bvh: &'a FlatBvh,
    geometry: Geometry<'a>,
    scene: &'a PathScene,
    traversal: Traversal,
}

/// Where a hit's surface is found: the triangles of one mesh, or the instances'.
#[derive(Clone, Copy)]
enum Geometry<'a> {
    Flat(&'a [Triangle]),
    Instanced(&'a InstancedBvh),
}

impl Geometry<'_> {
    /// `bvh_hit_surface` of `hit` on `ray`: `Hit::surface` for one mesh,
    /// `hits::instance_surface` for two levels.
    fn surface(&self, hit: &Hit, ray: &Ray) -> Option<SurfacePoint> {
        match self {
            Geometry::Flat(tris) => {
                let t = tris.get(hit.prim as usize)?;
                Some(hit.surface(t, Vec3::from(ray.dir)))
            }
            Geometry::Instanced(i) => {
                let (t, inst) = i.object_triangle(hit.prim)?;
                Some(instance_surface(hit, &t, inst, ray))
            }
        }
    }
}

/// The walk's answer and the stack it reuses.
struct Walker<'a> {
    tracer: &'a CpuPathTracer<'a>,
    stack: Vec<u32>,
    stats: PathStats,
}

impl Walker<'_> {
    fn closest(&mut self, ray: &Ray) -> Hit {
        self.stats.rays += 1;
        let opts = TraceOptions::closest(self.tracer.traversal);
        bvhtrace_core::trace_ray_with(self.tracer.bvh, ray, &opts, &mut self.stack).0
    }

    /// `path_blocked`.
    fn blocked(&mut self, ray: &Ray) -> bool {
        self.stats.rays += 1;
        let opts = TraceOptions::any(self.tracer.traversal);
        let prim = bvhtrace_core::trace_ray_with(self.tracer.bvh, ray, &opts, &mut self.stack)
            .0
            .prim;
        if prim == INCOMPLETE {
            self.stats.incomplete += 1;
        }
        prim != MISS && prim != INVALID_RAY
    }
}

fn black(v: Vec3) -> bool {
    !(v.x > 0.0 || v.y > 0.0 || v.z > 0.0)
}

fn scale(v: Vec3, s: f32) -> Vec3 {
    Vec3::new(v.x * s, v.y * s, v.z * s)
}

impl<'a> CpuPathTracer<'a> {
    /// The tracer of `bvh` (one mesh, built over `triangles`) shading with `scene`, its rays
    /// walked by `traversal` (every walk answers the same). An error when the shading data
    /// does not number the tree's primitives, or the wide walk is asked of a tree without
    /// its wide layout (`FlatBvh::build_wide`).
    pub fn new(
        bvh: &'a FlatBvh,
        triangles: &'a [Triangle],
        scene: &'a PathScene,
        traversal: Traversal,
    ) -> Result<CpuPathTracer<'a>, PathError> {
        if bvh.is_instanced() || triangles.len() != crate::scene::primitives(bvh) {
            return Err(PathError::Scene(format!(
                "{} triangles given, the tree has {} primitives{} (two levels: \
                 CpuPathTracer::instanced)",
                triangles.len(),
                crate::scene::primitives(bvh),
                if bvh.is_instanced() {
                    " in two levels"
                } else {
                    ""
                }
            )));
        }
        if scene.prims.len() != triangles.len() {
            return Err(PathError::Scene(format!(
                "the shading data has {} primitives, the tree {}",
                scene.prims.len(),
                triangles.len()
            )));
        }
        if traversal.is_wide() && bvh.wide().is_none() {
            return Err(PathError::Setting(
                "the wide walk needs the tree's wide layout (FlatBvh::build_wide)".into(),
            ));
        }
        Ok(CpuPathTracer {
            bvh,
            geometry: Geometry::Flat(triangles),
            scene,
            traversal,
        })
    }

    /// The tracer of a two-level BVH (instances over meshes), shading with `scene` made
    /// over the flattened scene (whose triangles the instances number in the same order).
    /// An error as for [`CpuPathTracer::new`].
    pub fn instanced(
        bvh: &'a InstancedBvh,
        scene: &'a PathScene,
        traversal: Traversal,
    ) -> Result<CpuPathTracer<'a>, PathError> {
        if scene.prims.len() as u64 != bvh.instanced_primitives() {
            return Err(PathError::Scene(format!(
                "the shading data has {} primitives, the instances {}",
                scene.prims.len(),
                bvh.instanced_primitives()
            )));
        }
        if traversal.is_wide() && bvh.bvh().wide().is_none() {
            return Err(PathError::Setting(
                "the wide walk needs the tree's wide layout (InstancedBvh::build_wide)".into(),
            ));
        }
        Ok(CpuPathTracer {
            bvh: bvh.bvh(),
            geometry: Geometry::Instanced(bvh),
            scene,
            traversal,
        })
    }

    /// Adds sample `params.sample` of every pixel to `accum` (started over at sample 0),
    /// on all threads of the current rayon pool.
    pub fn add_sample(&self, params: &PathParams, accum: &mut Accumulation) -> PathStats {
        let w = params.width as usize;
        accum.resize(params.width, params.height);
        let stats: Vec<PathStats> = (accum.sums.par_chunks_mut(w.max(1)).enumerate())
            .map(|(y, row)| {
                let mut walker = Walker {
                    tracer: self,
                    stack: Vec::new(),
                    stats: PathStats::default(),
                };
                for (x, sum) in row.iter_mut().enumerate() {
                    let mut c = walker.radiance(params, x as u32, y as u32);
                    let big = 3.0e38;
                    if !(c.x.abs() <= big && c.y.abs() <= big && c.z.abs() <= big) {
                        walker.stats.not_finite += 1;
                        c = Vec3::ZERO;
                    }
                    let s = if params.sample > 0 { *sum } else { [0.0; 4] };
                    *sum = [s[0] + c.x, s[1] + c.y, s[2] + c.z, s[3] + 1.0];
                }
                walker.stats
            })
            .collect();
        stats.into_iter().fold(PathStats::default(), |a, b| a + b)
    }
}

impl Walker<'_> {
    /// `path_radiance`.
    fn radiance(&mut self, p: &PathParams, x: u32, y: u32) -> Vec3 {
        let scene = self.tracer.scene;
        let mut r = Rng::new(y * p.width + x, p.sample, p.seed);
        let jx = r.uniform();
        let jy = r.uniform();
        let px = (2.0 * (x as f32 + jx) / p.width as f32 - 1.0) * p.tan_half_fov * p.aspect;
        let py = (1.0 - 2.0 * (y as f32 + jy) / p.height as f32) * p.tan_half_fov;
        let (f, rt, up) = (p.forward, p.right, p.up);
        let dir = normalize(Vec3::new(
            f[0] + rt[0] * px + up[0] * py,
            f[1] + rt[1] * px + up[1] * py,
            f[2] + rt[2] * px + up[2] * py,
        ));
        let mut ray = Ray::with_interval(Vec3::from(p.eye), dir, 0.0, FAR);
        let env = Vec3::from(p.env);
        let sun = Vec3::from(p.sun);
        let sun_dir = Vec3::from(p.sun_dir);
        let mut radiance = Vec3::ZERO;
        let mut throughput = Vec3::ONE;
        let mut last_pdf = 0.0;
        let mut last_n = Vec3::ZERO;
        let has_env = !black(env);
        for depth in 0..p.max_depth {
            let hit = self.closest(&ray);
            let dir = Vec3::from(ray.dir);
            if hit.prim == INCOMPLETE {
                self.stats.incomplete += 1;
                break;
            }
            if hit.prim >= INVALID_RAY {
                if let (true, Some(map)) = (has_env, &scene.environment) {
                    let (l, pdf) = map.lookup(dir);
                    let w = if depth > 0 { mis(last_pdf, pdf) } else { 1.0 };
                    radiance += scale(throughput * (l * env), w);
                    break;
                }
                let mut w = 1.0;
                if depth > 0 && has_env {
                    w = mis(last_pdf, dot(last_n, dir).max(0.0) / PI);
                }
                radiance += scale(throughput * env, w);
                break;
            }
            let Some(s) = self.tracer.geometry.surface(&hit, &ray) else {
                break;
            };
            let n = s.normal;
            let [mi, li] = scene.prims[hit.prim as usize];
            let m = textured(
                &scene.materials[mi as usize],
                &scene.textures,
                hit.prim,
                hit.u,
                hit.v,
            );
            let emissive = Vec3::from(m.emissive);
            let front = match scene.lights.get(li as usize) {
                Some(lt) if li != NO_LIGHT => {
                    dot(cross(Vec3::from(lt.e1), Vec3::from(lt.e2)), dir) < 0.0
                }
                _ => true,
            };
            if !black(emissive) && front {
                let mut w = 1.0;
                if depth > 0 && li != NO_LIGHT {
                    let cos_l = dot(n, dir).abs();
                    let light_pdf = scene.lights[li as usize].pdf_area * (hit.t * hit.t) / cos_l;
                    w = mis(last_pdf, light_pdf);
                }
                radiance += scale(throughput * emissive, w);
            }
            let wo = Vec3::new(-dir.x, -dir.y, -dir.z);
            let lobes = &m;

            if !black(sun) {
                let e = eval(lobes, n, wo, sun_dir);
                if e.pdf > 0.0 && !self.blocked(&Ray::with_interval(s.origin, sun_dir, 0.0, FAR)) {
                    radiance += throughput * (e.value * sun);
                }
            }
            if let (true, Some(map)) = (has_env, &scene.environment) {
                let (u0, u1, u2) = (r.uniform(), r.uniform(), r.uniform());
                let (wi, l, pdf) = map.sample(u0, u1, u2);
                let e = eval(lobes, n, wo, wi);
                if e.pdf > 0.0
                    && pdf > 0.0
                    && !self.blocked(&Ray::with_interval(s.origin, wi, 0.0, FAR))
                {
                    let w = mis(pdf, e.pdf) / pdf;
                    radiance += scale(throughput * (e.value * (l * env)), w);
                }
            }
            if has_env && scene.environment.is_none() {
                let wi = Frame::new(n).cosine(&mut r);
                let env_pdf = dot(n, wi) / PI;
                let e = eval(lobes, n, wo, wi);
                if e.pdf > 0.0
                    && env_pdf > 0.0
                    && !self.blocked(&Ray::with_interval(s.origin, wi, 0.0, FAR))
                {
                    let w = mis(env_pdf, e.pdf) / env_pdf;
                    radiance += scale(throughput * (e.value * env), w);
                }
            }
            if !scene.lights.is_empty() {
                radiance += self.light_sample(&mut r, lobes, s.origin, n, wo, throughput);
            }
            let wi = sample(lobes, n, wo, &mut r);
            let e = eval(lobes, n, wo, wi);
            if e.pdf.is_nan() || e.pdf <= 0.0 || black(e.value) {
                break;
            }
            let v = e.value;
            throughput *= Vec3::new(v.x / e.pdf, v.y / e.pdf, v.z / e.pdf);
            last_pdf = e.pdf;
            last_n = n;
            if depth >= 2 {
                let survive = throughput.x.max(throughput.y.max(throughput.z)).min(0.95);
                if r.uniform() >= survive {
                    break;
                }
                throughput = scale(throughput, 1.0 / survive);
            }
            ray = Ray::with_interval(s.origin, wi, 0.0, FAR);
        }
        radiance
    }

    /// One emissive triangle chosen by power, a uniform point on it, its shadow ray.
    fn light_sample(
        &mut self,
        r: &mut Rng,
        lobes: &PathMaterial,
        origin: Vec3,
        n: Vec3,
        wo: Vec3,
        throughput: Vec3,
    ) -> Vec3 {
        let lights = &self.tracer.scene.lights;
        let u = r.uniform();
        let (mut lo, mut hi) = (0usize, lights.len() - 1);
        while lo < hi {
            let mid = (lo + hi) / 2;
            if u < lights[mid].cdf {
                hi = mid;
            } else {
                lo = mid + 1;
            }
        }
        let light = &lights[lo];
        let su = r.uniform().sqrt();
        let b1 = 1.0 - su;
        let b2 = r.uniform() * su;
        let (v0, e1, e2) = (
            Vec3::from(light.v0),
            Vec3::from(light.e1),
            Vec3::from(light.e2),
        );
        let q = Vec3::new(
            v0.x + e1.x * b1 + e2.x * b2,
            v0.y + e1.y * b1 + e2.y * b2,
            v0.z + e1.z * b1 + e2.z * b2,
        );
        let d = Vec3::new(q.x - origin.x, q.y - origin.y, q.z - origin.z);
        let dist2 = dot(d, d);
        let dist = dist2.sqrt();
        let wi = Vec3::new(d.x / dist, d.y / dist, d.z / dist);
        let nl = normalize(cross(e1, e2));
        let cos_l = dot(nl, wi).abs();
        let e = eval(lobes, n, wo, wi);
        if !(e.pdf > 0.0 && cos_l > 0.0) || dot(nl, wi) > 0.0 {
            return Vec3::ZERO;
        }
        let toward = if dot(nl, wi) > 0.0 { -nl } else { nl };
        let target = offset_ray_origin(q, toward);
        let dt = Vec3::new(
            target.x - origin.x,
            target.y - origin.y,
            target.z - origin.z,
        );
        if self.blocked(&Ray::with_interval(origin, dt, 0.0, 1.0)) {
            return Vec3::ZERO;
        }
        let light_pdf = light.pdf_area * dist2 / cos_l;
        let w = mis(light_pdf, e.pdf) / light_pdf;
        let scene = self.tracer.scene;
        let lm = &scene.materials[scene.prims[light.prim as usize][0] as usize];
        let mut emission = Vec3::from(light.emission);
        if lm.emissive_tex != NO_TEXTURE {
            emission = Vec3::from(textured(lm, &scene.textures, light.prim, b1, b2).emissive);
        }
        scale(throughput * (e.value * emission), w)
    }
}

/// The mean over the pixels of their mean radiance's luminance (the shader's weights): a
/// figure for reports and tests on an image.
pub fn mean_luminance(accum: &Accumulation) -> f64 {
    let n = accum.sums.len().max(1) as f64;
    (accum.sums.iter())
        .map(|s| f64::from(luminance(Vec3::new(s[0], s[1], s[2])) / s[3].max(1.0)))
        .sum::<f64>()
        / n
}
