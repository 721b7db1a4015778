//! Rays and hits as they travel to and from the GPU (one layout for both sides).

use bytemuck::{Pod, Zeroable};
use glam::Vec3;

/// `Hit::prim` of a ray that hit nothing.
pub const MISS: u32 = u32::MAX;
/// `Hit::prim` of a ray that could not be traced (a NaN or infinite origin or direction,
/// a zero direction, or a NaN `t_min`/`t_max`): a miss, flagged.
pub const INVALID_RAY: u32 = u32::MAX - 1;
/// `Hit::prim` written by a GPU kernel for a ray that spent its loop-trip budget before its
/// answer was certain (see `TRIP_LIMIT` in `shaders/traverse_common.wgsl`): never
/// returned by the CPU traversals, nor by `bvhtrace_gpu::GpuBvh::trace`, which finishes
/// such rays on the CPU twin. Callers of `GpuBvh::record` see it and finish them.
pub const INCOMPLETE: u32 = u32::MAX - 2;

/// A ray with its parametric interval. Hits are accepted for `t_min <= t < t_max`.
/// GPU layout: WGSL `Ray` in `shaders/types.wgsl` (32 bytes).
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct Ray {
    /// Ray origin.
    pub origin: [f32; 3],
    /// Smallest accepted hit distance (inclusive).
    pub t_min: f32,
    /// Direction; need not be normalised, `t` is in its units.
    pub dir: [f32; 3],
    /// Largest hit distance (exclusive); may be `f32::INFINITY`.
    pub t_max: f32,
}

impl Ray {
    /// A ray over `[0, inf)`.
    pub fn new(origin: Vec3, dir: Vec3) -> Self {
        Self::with_interval(origin, dir, 0.0, f32::INFINITY)
    }

    /// A ray over `[t_min, t_max)`.
    pub fn with_interval(origin: Vec3, dir: Vec3, t_min: f32, t_max: f32) -> Self {
        Ray {
            origin: origin.to_array(),
            t_min,
            dir: dir.to_array(),
            t_max,
        }
    }

    /// True when the ray can be traced: finite origin and direction, a non-zero direction,
    /// and interval ends that are not NaN.
    pub fn is_valid(&self) -> bool {
        let o = Vec3::from(self.origin);
        let d = Vec3::from(self.dir);
        o.is_finite()
            && d.is_finite()
            && d != Vec3::ZERO
            && !self.t_min.is_nan()
            && !self.t_max.is_nan()
    }

    /// The point at distance `t`.
    pub fn at(&self, t: f32) -> Vec3 {
        Vec3::from(self.origin) + t * Vec3::from(self.dir)
    }
}

/// The answer for one ray. GPU layout: WGSL `Hit` in `shaders/types.wgsl` (16 bytes).
///
/// `prim` is the index of the triangle in the builder's input order, [`MISS`] or
/// [`INVALID_RAY`]. `u` and `v` are the barycentric weights of the triangle's second and
/// third corners (the first corner's is `1 - u - v`). For a miss, `t` is `t_max`'s value
/// as given and `u = v = 0`; never NaN.
#[repr(C)]
#[derive(Clone, Copy, Debug, PartialEq, Pod, Zeroable)]
pub struct Hit {
    /// Hit distance along the ray, in units of the ray's direction.
    pub t: f32,
    /// Primitive index, or [`MISS`] / [`INVALID_RAY`].
    pub prim: u32,
    /// Barycentric weight of corner 1.
    pub u: f32,
    /// Barycentric weight of corner 2.
    pub v: f32,
}

impl Hit {
    /// A miss for a ray with this `t_max`.
    pub fn miss(t_max: f32) -> Self {
        Hit {
            t: t_max,
            prim: MISS,
            u: 0.0,
            v: 0.0,
        }
    }

    /// True when a triangle was hit.
    pub fn is_hit(&self) -> bool {
        self.prim < INVALID_RAY
    }
}

/// Per-ray work counters, as the heatmap and the benchmarks read them.
#[repr(C)]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Pod, Zeroable)]
pub struct Counters {
    /// Nodes whose box was tested against the ray.
    pub nodes: u32,
    /// Triangles tested against the ray.
    pub tris: u32,
}

impl std::ops::AddAssign for Counters {
    fn add_assign(&mut self, o: Self) {
        self.nodes += o.nodes;
        self.tris += o.tris;
    }
}
