//! bvhtrace core: build a SAH BVH on the CPU, flatten it into the layout the GPU kernels
//! read, and trace rays through it on the CPU with the same arithmetic as the kernels.
//!
//! The flow: [`mesh::TriangleMesh`] → [`build::build`] → [`build::BuildTree`] →
//! [`flat::FlatBvh::flatten`] → [`traverse::trace_rays`] (or the GPU crate), checked
//! against [`oracle`]. The layout is documented once, in [`flat`].

// `!(a <= b)` is how the tests reject NaN along with the false case: keep it readable as is.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
#![warn(missing_docs)]

pub mod alpha;
pub mod build;
pub mod collapse;
pub mod cost;
pub mod curves;
pub mod flat;
pub mod geometry;
pub mod hits;
pub mod instance;
pub mod intersect;
pub mod masks;
pub mod mesh;
pub mod motion;
pub mod oracle;
pub mod precision;
pub mod ray;
pub mod stats;
pub mod surface;
pub mod traverse;
pub mod wide;

pub use build::reinsert::{ReinsertOptions, optimize, optimize_with};
pub use build::{BuildError, BuildOptions, BuilderKind, build};
pub use curves::{CurveBvh, CurveError, CurveKind, CurveRay, CurveSegment, Curves};
pub use flat::{FlatBvh, FlatInstance, FlatNode, FlatTriangle, RefitError};
pub use geometry::Aabb;
pub use hits::{InstanceHit, InstanceTable};
pub use instance::{Instance, InstanceError, InstancedBvh};
pub use masks::MaskTables;
pub use mesh::{MeshError, Triangle, TriangleMesh};
pub use motion::{MotionBvh, MotionError, MotionMesh, TimeBounds};
pub use precision::Precision;
pub use ray::{Counters, Hit, INCOMPLETE, INVALID_RAY, MISS, Ray};
pub use stats::BvhStats;
pub use traverse::{
    Candidate, HitFilter, Query, TraceOptions, TraceOutput, TracePhases, Traversal, WalkCost,
    brute_force, brute_force_filtered, trace_ray, trace_ray_cost, trace_ray_filtered, trace_ray_in,
    trace_ray_with, trace_rays, trace_rays_filtered, trace_rays_in,
};
pub use wide::{WideBvh, WideNode};
