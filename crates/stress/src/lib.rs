//! Numerical stress cases for bvhtrace (`bvhtrace stress`): where the f32 BVH traversal is
//! exact, where it is only as good as f32 can be, and where precision runs out.
//!
//! * [`select_cases`] and [`cases_sized`] generate each [`Case`] ([`CaseOptions`]: the
//!   size, the shared scenes folder): a scene (triangles), rays, and what each ray's
//!   answer should be ([`Expect`]): known exactly, or whatever the f64 oracle
//!   ([`bvhtrace_core::oracle`]) says for the f32 input.
//! * [`run_case`] builds the BVH (two levels, an [`bvhtrace_core::InstancedBvh`], when
//!   the case has [`Case::instancing`]) and traces the rays with every walk
//!   ([`traversals`]) and query on the CPU twins and on every device of [`Backends`]
//!   (the tracers its caller's [`DeviceTracers`] factories open: this crate opens no
//!   backend), and compares: against the known answers, against the f64 oracle
//!   (differences classified as *f32-indeterminate* or *wrong* with
//!   [`bvhtrace_core::oracle::f32_indeterminate`] and
//!   [`bvhtrace_core::oracle::f32_t_error_bound`]), against the f32 brute force (what
//!   every traversal must return), and each device of our walks against the CPU twins
//!   bit for bit.
//! * [`table_header`], [`table_rows`] and [`format_table`]: the report as a table; every
//!   report serialises to JSON. The command line (`bvhtrace stress`) is the CLI's.
//!
//! `GUARANTEES.md` beside this crate states what holds and where precision runs out, with
//! the figures this crate measured.

// `!(a <= b)` rejects NaN along with the false case: keep it readable as is.
#![allow(clippy::neg_cmp_op_on_partial_ord)]
#![warn(missing_docs)]

mod cases;
mod curves;
pub mod geom;
mod motion;
pub mod offset;
mod report;
mod runner;
#[cfg(feature = "wgpu")]
pub mod wgpu_trees;

use bvhtrace_core::motion::MovingInstance;
use bvhtrace_core::{BuildOptions, Curves, Instance, Ray, Triangle};
use serde::Serialize;

pub use cases::{CASE_GROUPS, CaseOptions, cases_sized, select_cases};
pub use geom::flatten_instances;
pub use offset::offset_ray_origin;
pub use report::{format_table, table_header, table_rows};
pub use runner::{
    Backends, CPU_LAYOUT_ROWS, CaseReport, DeviceTracers, Differences, MovingTree, OpenCurves,
    OpenMotion, OpenTracer, PrecisionRow, RunReport, TraceTimed, run_case, run_case_with_timeout,
    traversals,
};

/// How big to make the cases: `Quick` for the tests (seconds), `Full` for the command.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize)]
pub enum Size {
    /// Small meshes and ray sets, for the test suite.
    Quick,
    /// The sizes `bvhtrace stress` runs by default.
    Full,
}

/// What a ray's answer should be.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub enum Expect {
    /// Whatever the f64 oracle says (compared on the oracle sample).
    Oracle,
    /// Some triangle: the ray starts strictly inside a closed surface (checked with the
    /// oracle when the case is made), so a miss is an escape through a crack.
    MustHit,
    /// Exactly this primitive (closest-hit), or some hit (any-hit).
    Prim(u32),
    /// A miss (`MISS`, not `INVALID_RAY`).
    Miss,
    /// `INVALID_RAY`: a NaN or infinite origin or direction, a zero direction, or a NaN
    /// interval end.
    Invalid,
    /// A secondary ray leaving primitive `origin` from its hit point, with the robust
    /// origin offset or without it: a closest hit on `origin` is a self-hit. Otherwise the
    /// oracle decides.
    Secondary {
        /// The primitive the ray leaves.
        origin: u32,
        /// True when the origin was moved with [`offset_ray_origin`].
        offset: bool,
    },
    /// A precision-limit ray: the oracle decides, and [`Case::precision`] says which
    /// surface the intended (unrounded) geometry puts first.
    Surface,
    /// Only the general contract (no NaN, the interval, GPU = CPU).
    Unspecified,
}

/// What rounding the intended geometry to f32 did to a case's input.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct InputInfo {
    /// The f32 input is exactly the intended geometry (every coordinate representable).
    pub exact: bool,
    /// Distinct vertices that rounding merged.
    pub merged_vertices: usize,
    /// Triangles of exactly zero area in the f32 input.
    pub zero_area_triangles: usize,
}

/// One surface pair of the precision-limit case: two parallel squares `gap` apart.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct SurfacePair {
    /// Translation of the pair (its centre is about `offset * (1, 1, 1)`).
    pub offset: f64,
    /// Intended distance between the two surfaces.
    pub gap: f64,
    /// Corners of the lower surface that rounded onto the upper surface's plane position
    /// exactly (the f32 input merged them).
    pub merged_corners: usize,
}

/// Which pair a precision-limit ray probes, from where, and what it should hit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
pub struct SurfaceProbe {
    /// Index into [`PrecisionSetup::pairs`].
    pub pair: u32,
    /// True when the ray starts at distance `offset` from the surfaces (a camera at the
    /// world origin), false when at distance 1 (a camera moved with the geometry).
    pub far: bool,
    /// The primitive the unrounded f64 geometry puts first along this (f32) ray, or
    /// `MISS`.
    pub intended: u32,
}

/// The precision-limit case's bookkeeping (see [`Expect::Surface`]).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct PrecisionSetup {
    /// The surface pairs.
    pub pairs: Vec<SurfacePair>,
    /// For each primitive: its pair, and true for the upper surface (the one the rays
    /// meet first).
    pub prim_surface: Vec<(u32, bool)>,
    /// For each ray of the case: what it probes (rays of other kinds have none).
    pub probes: Vec<Option<SurfaceProbe>>,
}

/// A stress case: a scene, rays, and what their answers should be.
#[derive(Clone, Debug)]
pub struct Case {
    /// Short name (`offset-1e5`); `--case` selects by name or by group prefix.
    pub name: String,
    /// What the case exercises.
    pub description: String,
    /// The scene.
    pub tris: Vec<Triangle>,
    /// The rays.
    pub rays: Vec<Ray>,
    /// One expectation per ray.
    pub expect: Vec<Expect>,
    /// How to build the BVH.
    pub build: BuildOptions,
    /// Whether any-hit queries are traced too.
    pub any_hit: bool,
    /// What rounding did to the input.
    pub input: InputInfo,
    /// Most rays compared with the oracle (the oracle is O(rays x triangles)).
    pub oracle_budget: usize,
    /// Things worth saying (a mesh skipped, a point not verified inside...).
    pub notes: Vec<String>,
    /// The precision-limit bookkeeping, for that case only.
    pub precision: Option<PrecisionSetup>,
    /// False for cases measured beyond the guaranteed range (`scale-limit-*`): only the
    /// unconditional guarantees (no crash, no NaN, the hit contract, GPU = CPU) are held
    /// against them; their accuracy is reported, not required.
    pub guaranteed: bool,
    /// Two levels: when set, the runner builds an [`bvhtrace_core::InstancedBvh`] over
    /// these meshes and instances instead of one BVH over `tris`, and `tris` holds the
    /// flattened scene ([`flatten_instances`]: every instance's triangles in world space,
    /// in primitive order), for the table and the inside tests. The oracle traces each
    /// instance's mesh with the ray as the walks transform it (see `GUARANTEES.md`).
    pub instancing: Option<Instancing>,
    /// A moving scene traced at one time: the runner builds its moving tree (with each of
    /// [`bvhtrace_core::TimeBounds`]) and traces every ray at [`Motion::time`], and `tris`
    /// holds the scene at that time (for a mesh, [`bvhtrace_core::MotionMesh::at`]: the
    /// triangles the walks test), which the oracle, the brute force and the inside tests
    /// judge.
    pub motion: Option<Motion>,
    /// Curves beside `tris` (which may be empty): the runner builds a
    /// [`bvhtrace_core::CurveBvh`] over both, numbering the segments after the triangles,
    /// and judges its answers against the known ones and its own brute force (there is no
    /// f64 oracle for curves).
    pub curves: Option<Curves>,
}

/// What moves in a case, and when its rays are traced (see [`Case::motion`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Motion {
    /// The moving scene.
    pub scene: MovingScene,
    /// The time every ray is traced at (clamped to `[0, 1]` by the walks).
    pub time: f32,
}

/// A moving scene: one mesh, or meshes placed by moving instances.
#[derive(Clone, Debug, PartialEq)]
pub enum MovingScene {
    /// The triangles at each time step, spread evenly over the shutter `[0, 1]`; the
    /// runner builds a [`bvhtrace_core::MotionBvh`].
    Mesh(Vec<Vec<Triangle>>),
    /// Static meshes placed by instances whose transforms move; the runner builds a
    /// [`bvhtrace_core::motion::MotionInstancedBvh`]. The case's [`Case::instancing`]
    /// holds the same meshes placed where the instances are at the case's time, and each
    /// instance is judged in its mesh's space with the ray as the walks take it there
    /// ([`MovingInstance::world_to_object_at`]).
    Instances {
        /// The meshes.
        meshes: Vec<Vec<Triangle>>,
        /// The instances, numbering primitives as [`Case::instancing`] does.
        instances: Vec<MovingInstance>,
    },
}

/// The two levels of an instanced case (see [`Case::instancing`]).
#[derive(Clone, Debug, PartialEq)]
pub struct Instancing {
    /// Each mesh's triangles, in object space.
    pub meshes: Vec<Vec<Triangle>>,
    /// The placements; primitive ids are numbered instance by instance in this order.
    pub instances: Vec<Instance>,
}

impl Case {
    /// A case with default build options, any-hit on, no notes.
    pub fn new(name: impl Into<String>, description: impl Into<String>) -> Case {
        Case {
            name: name.into(),
            description: description.into(),
            tris: Vec::new(),
            rays: Vec::new(),
            expect: Vec::new(),
            build: BuildOptions::default(),
            any_hit: true,
            input: InputInfo {
                exact: true,
                ..Default::default()
            },
            oracle_budget: 4096,
            notes: Vec::new(),
            precision: None,
            guaranteed: true,
            instancing: None,
            motion: None,
            curves: None,
        }
    }

    /// A two-level case: `tris` is the flattened scene ([`flatten_instances`]), no rays
    /// yet.
    pub fn instanced(
        name: impl Into<String>,
        description: impl Into<String>,
        meshes: Vec<Vec<Triangle>>,
        instances: Vec<Instance>,
    ) -> Case {
        let mut c = Case::new(name, description);
        c.tris = flatten_instances(&meshes, &instances);
        c.instancing = Some(Instancing { meshes, instances });
        c
    }

    /// Adds rays with one expectation.
    pub fn push_rays(&mut self, rays: impl IntoIterator<Item = Ray>, expect: Expect) {
        for r in rays {
            self.rays.push(r);
            self.expect.push(expect);
        }
    }

    /// Number of rays with each kind of expectation that needs no oracle.
    pub fn count(&self, pred: impl Fn(&Expect) -> bool) -> usize {
        self.expect.iter().filter(|e| pred(e)).count()
    }
}
