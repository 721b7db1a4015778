//! Your own WGSL over an upload: the traversal library, composed for what the upload
//! holds, with the same calls on every shape (`bvh_trace_closest`, `bvh_trace_any`,
//! `bvh_hit_surface`, the instance helpers).

use bvhtrace_core::{Precision, Traversal};

use crate::compose::{Entries, ModuleSet, WalkSet};
use crate::pages::Pages;
use crate::ray_query;
use crate::shaders;
use crate::storage::BvhStorage;
use crate::walks::{short_stack_size, walk};

/// What a traversal library ([`wgsl_library`]) is composed for: what the upload it reads
/// holds, and the walk its calls take. With bvhtrace-gpu, `GpuBvh::wgsl_library` fills it
/// in from the upload, and `GpuBvh::bind_group_for` refuses a library of another shape.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct LibraryShape {
    /// Where the BVH is read from (`GpuBvh::storage`).
    pub storage: BvhStorage,
    /// A two-level BVH (`FlatBvh::is_instanced`): the instances' binding (4) and the
    /// instance walk are composed in.
    pub instanced: bool,
    /// The walk `bvh_trace_closest` and `bvh_trace_any` take, and so the layout and
    /// arrays the library reads ([`crate::walks::WALKS`]). A short stack's size is
    /// clamped to `1..=32`.
    pub traversal: Traversal,
    /// The triangle test ([`crate::compose::triangle_wgsl`]).
    pub precision: Precision,
    /// The device's ray queries walk its own acceleration structure instead
    /// ([`LibraryShape::ray_queries`], [`crate::ray_query`]): the TLAS at binding 0, the
    /// triangles in buffers; `traversal` and `precision` are not read.
    pub ray_queries: bool,
    /// The BVH has alpha masks (`FlatBvh::masks`): their binding (5) and test are
    /// composed in, so your walks cut masked candidates as the kernels do.
    pub masks: bool,
    /// Your filter ([`LibraryShape::with_filter`]): the name of a WGSL function
    /// `fn(BvhCandidate) -> bool` of your shader, asked about every candidate that would
    /// become the hit.
    pub filter: Option<&'static str>,
    /// How the upload's arrays are split over bindings ([`crate::pages`]; `GpuBvh` fills
    /// it in): [`Pages::ONE`] unless the tree is larger than one of the device's bindings.
    pub pages: Pages,
}

impl LibraryShape {
    /// The library of `traversal` for a BVH in `storage`, one mesh or two levels
    /// (`instanced`), with the default triangle test.
    pub fn new(storage: BvhStorage, instanced: bool, traversal: Traversal) -> LibraryShape {
        LibraryShape {
            storage,
            instanced,
            traversal,
            precision: Precision::WatertightF32,
            ray_queries: false,
            masks: false,
            filter: None,
            pages: Pages::ONE,
        }
    }

    /// The same library with every candidate that would become the hit passed to your
    /// WGSL function `name`, `fn(c: BvhCandidate) -> bool` (`candidate.wgsl`: the
    /// primitive id, instance, mesh primitive, `t`, `u`, `v`): a candidate it rejects is
    /// as if the ray had missed that triangle, and the walk goes on. The CPU walks take
    /// the same rule as a closure (`bvhtrace_core::trace_rays_filtered`). Not for the
    /// device's ray queries.
    pub fn with_filter(self, name: &'static str) -> LibraryShape {
        LibraryShape {
            filter: Some(name),
            ..self
        }
    }

    /// The library that calls the device's ray queries (`enable wgpu_ray_query;`, needs
    /// wgpu's `EXPERIMENTAL_RAY_QUERY`) for one mesh or two levels: the same calls and
    /// result struct as the walks' libraries, bound to a `RayQueryBvh` (bvhtrace-gpu).
    pub fn ray_queries(instanced: bool) -> LibraryShape {
        LibraryShape {
            ray_queries: true,
            ..LibraryShape::new(BvhStorage::Buffers, instanced, Traversal::FullStack)
        }
    }

    /// The files it is composed of: the walk's, its layout's and storage's bindings, and
    /// the instances' when `instanced`.
    pub fn module_set(&self) -> ModuleSet {
        ModuleSet {
            walks: WalkSet::of(self.traversal),
            instances: self.instanced,
            masks: self.masks,
            filter: self.filter,
            pages: self.pages,
            ..ModuleSet::everything(self.storage, self.precision, Entries::None)
        }
    }

    /// The call of its walk on `ray` and `lane`, any hit or closest.
    fn walk_call(&self, any_hit: bool) -> String {
        let k = short_stack_size(self.traversal).map_or(String::new(), |k| format!("{k}u"));
        walk(self.traversal).call_with("ray", &any_hit.to_string(), &k, "lane")
    }
}

impl std::fmt::Display for LibraryShape {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let levels = if self.instanced {
            "two levels"
        } else {
            "one mesh"
        };
        let masks = if self.masks { ", alpha masks" } else { "" };
        if self.ray_queries {
            return write!(f, "{levels}{masks}, the device's ray queries");
        }
        let layout = if self.traversal.is_wide() {
            "wide"
        } else {
            "binary"
        };
        write!(
            f,
            "{levels}{masks}, {layout} layout in {:?}, {} walk",
            self.storage,
            self.traversal.name()
        )?;
        match self.pages.is_one() {
            true => Ok(()),
            false => write!(f, ", split into pages ({:?})", self.pages),
        }
    }
}

/// The traversal library composed for one [`LibraryShape`], with the BVH bindings in one
/// group: its WGSL ([`BvhLibrary::source`], also its `Display`) and what it was composed
/// for, which the bind group is checked against.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct BvhLibrary {
    shape: LibraryShape,
    group: u32,
    source: String,
}

impl BvhLibrary {
    /// The WGSL: prepend it to your shader.
    pub fn source(&self) -> &str {
        &self.source
    }

    /// What it was composed for.
    pub fn shape(&self) -> LibraryShape {
        self.shape
    }

    /// The group of its BVH bindings.
    pub fn group(&self) -> u32 {
        self.group
    }
}

impl std::fmt::Display for BvhLibrary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.source)
    }
}

/// The traversal library without entry points, for your own compute shader, composed for
/// what the upload holds (`shape`: with bvhtrace-gpu, `GpuBvh::wgsl_library` fills it in)
/// with the BVH bindings in `@group(bvh_group)`: 0 (nodes; the wide layout's for
/// [`Traversal::Wide`]), 1 (triangles), 2 (escape links, for the stackless and short-stack
/// walks) and 4 (instances, for two levels). With bvhtrace-gpu, bind
/// `GpuBvh::bind_group_for(&library)`, which refuses a library of another shape, and put its
/// `layout()` in your pipeline layout.
///
/// Every name it declares starts with `bvh_`, `Bvh` or `BVH_`; leave those to it. It
/// declares the structs (field by field the Rust types of `bvhtrace_core`)
///
/// * `BvhRay { origin: vec3<f32>, t_min: f32, dir: vec3<f32>, t_max: f32 }` (a
///   [`bvhtrace_core::Ray`]),
/// * `BvhHit { t: f32, prim: u32, u: f32, v: f32 }` (a [`bvhtrace_core::Hit`]: `prim` is
///   the triangle's index in the builder's input, numbered instance by instance for two
///   levels, or `BVH_MISS`, `BVH_INVALID_RAY` or `BVH_INCOMPLETE`; `u`, `v` the
///   barycentrics of corners 1 and 2),
/// * `BvhCounters { nodes: u32, tris: u32 }` (box and triangle tests of the ray),
/// * `BvhTraceResult { hit: BvhHit, counters: BvhCounters }`,
/// * `BvhSurface { origin: vec3<f32>, normal: vec3<f32> }`,
///
/// the same calls for every shape
///
/// * `bvh_trace_closest(ray: BvhRay, lane: u32) -> BvhTraceResult` and
///   `bvh_trace_any(ray: BvhRay, lane: u32) -> BvhTraceResult`: the shape's walk, where
///   `lane` is the invocation's `local_invocation_index` (the stacks live in workgroup
///   memory, `bvh_lane_stacks`, one per lane, for workgroups of at most [`STACK_LANES`](crate::walks::STACK_LANES)
///   invocations; create the pipeline with `zero_initialize_workgroup_memory: false`: the
///   walks write every entry before they read it),
/// * after a hit, until the invocation's next trace: `bvh_hit_surface(ray, hit) ->
///   BvhSurface` (where secondary rays leave it, in world space: the twin of
///   `Hit::surface` for one mesh and of `bvhtrace_core::hits::instance_surface` for two
///   levels), `bvh_hit_instance_index()`, `bvh_hit_user_id()` and
///   `bvh_hit_mesh_prim(hit)` (the instance, as `TraceOutput::instance_hit` gives it; 0,
///   0 and `hit.prim` for one mesh),
/// * `bvh_offset_ray_origin(p: vec3<f32>, n: vec3<f32>) -> vec3<f32>`, the rule of
///   `bvhtrace_core::surface::offset_ray_origin`,
///
/// and the walks themselves (`bvh_trace_full_stack(ray, any_hit, lane)`,
/// `bvh_trace_short_stack(ray, any_hit, k, lane)` or `bvh_trace_wide(ray, any_hit, lane)`,
/// whichever the shape's walk is).
///
/// Its pipeline-overridable constants, all optional:
///
/// * `BVH_TRIP_LIMIT: u32` (default unbounded): the most box and triangle tests one ray
///   may take. A ray that spends it returns `prim == BVH_INCOMPLETE`; trace it again on the
///   CPU with the same options (`bvhtrace_engine::tracer::finish_incomplete`). Set it only for a
///   CPU driver, which ends invocations that loop too long
///   ([`crate::device::CPU_DRIVER_TRIP_LIMIT`]); on GPUs no ray is ever incomplete. The wide walk
///   returns it too on a wide tree deeper than [`WIDE_STACK_GROUPS`](crate::walks::WIDE_STACK_GROUPS)` + 1` levels.
/// * `BVH_PARALLEL_RAYS: bool` (default true): false compiles out the box test's path for
///   rays with a zero direction component; only when you know no ray has one.
/// * `BVH_RAY_MASK: u32` (default `0xff`, two levels only): instances whose mask shares no
///   bit with it are passed through.
///
/// # Example
///
/// A shader that traces one ray per invocation with its own bindings in group 1:
///
/// ```
/// use bvhtrace_engine::core::Traversal;
/// use bvhtrace_engine::{BvhStorage, LibraryShape};
///
/// let my_shader = r#"
/// @group(1) @binding(0) var<storage, read_write> ids: array<u32>;
///
/// @compute @workgroup_size(64) // at most STACK_LANES
/// fn main(
///     @builtin(global_invocation_id) gid: vec3<u32>,
///     @builtin(local_invocation_index) lane: u32,
/// ) {
///     let x = f32(gid.x) * 0.01;
///     let ray = BvhRay(vec3<f32>(x, 0.0, 5.0), 0.0, vec3<f32>(0.0, 0.0, -1.0), 1e30);
///     let res = bvh_trace_closest(ray, lane);
///     ids[gid.x] = bvh_hit_user_id();
/// }
/// "#;
/// // Two levels in buffers, the stackless walk (with bvhtrace-gpu:
/// // `let library = gpu.wgsl_library(Traversal::Stackless, 0)?;`).
/// let shape = LibraryShape::new(BvhStorage::Buffers, true, Traversal::Stackless);
/// let library = bvhtrace_engine::wgsl_library(shape, 0);
/// let source = format!("{library}\n{my_shader}");
/// # let module = naga::front::wgsl::parse_str(&source).expect("parses");
/// # naga::valid::Validator::new(Default::default(), naga::valid::Capabilities::all())
/// #     .validate(&module)
/// #     .expect("validates");
/// // With bvhtrace-gpu:
/// // let group = gpu.bind_group_for(&library)?; // an error for another shape
/// // pipeline layout: [Some(group.layout()), Some(&my_group_1_layout)];
/// // pass.set_bind_group(0, group.group(), &[]);
/// ```
pub fn wgsl_library(shape: LibraryShape, bvh_group: u32) -> BvhLibrary {
    let (mut source, closest, any) = if shape.ray_queries {
        (
            ray_query::compose(
                &ray_query::files(shape.instanced, shape.masks, shape.pages),
                bvh_group,
            ),
            "bvh_trace_ray_query(ray, false)".to_string(),
            "bvh_trace_ray_query(ray, true)".to_string(),
        )
    } else {
        (
            shape.module_set().compose(bvh_group),
            shape.walk_call(false),
            shape.walk_call(true),
        )
    };
    source.push_str("// ---- library.wgsl ----\n");
    source.push_str(
        &shaders::LIBRARY
            .1
            .replace("BVH_LIBRARY_CLOSEST", &closest)
            .replace("BVH_LIBRARY_ANY", &any),
    );
    BvhLibrary {
        shape,
        group: bvh_group,
        source,
    }
}
