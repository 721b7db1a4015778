//! The WGSL kernels: composed at load time from the files in the repository's `shaders/`
//! folder, one file per concern, and specialised per pipeline with override constants.
//!
//! | file | concern | CPU twin |
//! |---|---|---|
//! | `types.wgsl` | `BvhNode`, `BvhWideNode`, `BvhTriangle`, `BvhRay`, `BvhHit`, `BvhCounters`, `BvhTraceResult` | `bvhtrace_core::{FlatNode, WideNode, FlatTriangle, Ray, Hit, Counters}` |
//! | `bvh_buffers.wgsl` or `bvh_textures.wgsl` | the binary layout's node binding (group 0 by default) and fetch functions ([`BvhStorage`]) | `FlatBvh` |
//! | `bvh_buffers_wide.wgsl` or `bvh_textures_wide.wgsl` | the wide layout's nodes (binding 0), in their place for the wide walk | `WideBvh` |
//! | `bvh_buffers_triangles.wgsl` or `bvh_textures_triangles.wgsl` | the triangles (binding 1) of either layout; for textures, the texel addressing too | `FlatBvh::triangles`, `WideBvh::triangles` |
//! | `ray.wgsl` | validity, `bvh_safe_inverse`, `bvh_prepare_ray`, `bvh_octant` | `Ray::is_valid`, `PreparedRay::new`, `flat::octant` |
//! | `surface.wgsl` | `bvh_offset_ray_origin`, for secondary rays | `surface::offset_ray_origin` |
//! | `box.wgsl` | conservative slab test | `intersect::intersect_box` |
//! | `triangle_hit.wgsl` | `BvhTriHit`, what every triangle test returns | `intersect::TriHit` |
//! | `triangle.wgsl` (or a [`Precision`] variant, [`triangle_wgsl`]) | watertight triangle test | `intersect::intersect_triangle` |
//! | `traverse_common.wgsl` | hit rule, leaf visit | `traverse::visit_leaf` |
//! | `traverse_instances.wgsl` | entering and leaving instances of a two-level BVH (folded away for one mesh) | `traverse::Space` |
//! | `bvh_instances.wgsl` or `bvh_no_instances.wgsl` | the instances (binding 4) of a two-level BVH, or the same names for one mesh | `FlatBvh::instances` |
//! | `traverse_stack.wgsl` | the per-lane stacks in workgroup memory, only for the full stack, the short stack and the wide walk | `Vec` / the ring of `traverse::short_stack` |
//! | `traverse_full_stack.wgsl` | `bvh_trace_full_stack(ray, any_hit, lane)` | `traverse::full_stack` |
//! | `traverse_short_stack.wgsl` | `bvh_trace_short_stack(ray, any_hit, k, lane)` (k = 0: stackless) | `traverse::short_stack` |
//! | `traverse_wide.wgsl` | `bvh_trace_wide(ray, any_hit, lane)`, only with the wide layout | `traverse::wide` |
//! | `library.wgsl` | only in [`wgsl_library`]: `bvh_trace_closest`, `bvh_trace_any` (the shape's walk), `bvh_hit_surface`, the hit's instance | `Hit::surface`, `hits::instance_surface`, `TraceOutput::instance_hit` |
//! | `bvh_buffers_escapes.wgsl` or `bvh_textures_escapes.wgsl` | the escape links (binding 2), only for the walks that read them | `FlatBvh::escapes` |
//! | `attribute_normals.wgsl` | per-vertex normals, only when the scene has them and the job uses them | - |
//! | `entry.wgsl` | what the entry points share: the overrides, `bvh_ray_index` | `traverse::trace_rays` |
//! | `entry_rays_buffer.wgsl` or `entry_rays_texture.wgsl` | where the rays come from and the hits go (`bvh_load_ray`, `bvh_store_hit`, `bvh_batch_len`; [`RayInput`]) | - |
//! | `entry_counters.wgsl` | the `counters` binding, only when counters are on | `trace_rays` with counters |
//! | `entry_walk.wgsl` | every entry point, specialised per walk and output (`bvh_trace_{full_stack,short_stack,wide}_{main,counted}`) | |
//!
//! [`wgsl_library`] composes the traversal library of one walk for what an upload holds
//! ([`LibraryShape`]: storage, one mesh or two levels, binary or wide layout), no entry
//! point, with `library.wgsl`'s calls (`bvh_trace_closest`, `bvh_trace_any`,
//! `bvh_hit_surface`), for use from your own shaders; [`kernel_source`] composes both binary
//! walks and every entry point (the everything-on module); [`crate::KernelKey::source`] composes
//! only what one pipeline needs. Every name the WGSL declares starts with `bvh_`, `Bvh`
//! or `BVH_`, so the library can be composed with a user's shader. The BVH storage is chosen by which bindings file is
//! composed in. Nothing is copied between variants: the stackless walk is the short-stack
//! function with `k = 0`, the query and `k` are pipeline-overridable constants (`BVH_ANY_HIT`,
//! `BVH_SHORT_STACK_SIZE`), counters are written only by the `*_counted` entry points, and
//! every entry point is one file specialised with its walk. The wide layout binds its own nodes at binding 0, so its walk is composed in
//! modules of its own, from the same ray, box, triangle, hit-rule, instance and stack files.

use bvhtrace_core::{Precision, Traversal};

/// Where the kernels read the BVH from. Both give bit-identical results.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum BvhStorage {
    /// Storage buffers in the exact layout of [`bvhtrace_core::flat`]
    /// (`bvh_buffers.wgsl`): the portable choice, and the one to bind from your own
    /// shaders when you already hold the buffers.
    #[default]
    Buffers,
    /// `Rgba32Uint`/`R32Uint` textures of [`TEXEL_ROW`] texels per row
    /// (`bvh_textures.wgsl`, `bvh_textures_wide.wgsl`). On lavapipe a texel fetch is a
    /// vector gather while a storage-buffer load is a per-lane scalar loop: traversal is
    /// about 2.5x faster.
    Textures,
}

impl BvhStorage {
    /// The WGSL file declaring this storage's binding of the binary layout's nodes and
    /// their fetch functions; [`BvhStorage::triangles_wgsl`] is composed after it.
    pub fn wgsl(&self) -> (&'static str, &'static str) {
        match self {
            BvhStorage::Buffers => ("bvh_buffers.wgsl", BVH_BUFFERS_WGSL),
            BvhStorage::Textures => ("bvh_textures.wgsl", BVH_TEXTURES_WGSL),
        }
    }

    /// The WGSL file declaring this storage's binding of the wide layout's nodes
    /// (`WideBvh::nodes`, binding 0) and `bvh_load_wide_node`/`bvh_load_wide_links`, in
    /// place of [`BvhStorage::wgsl`] for the wide walk; [`BvhStorage::triangles_wgsl`] is
    /// composed after it.
    pub fn wide_wgsl(&self) -> (&'static str, &'static str) {
        match self {
            BvhStorage::Buffers => ("bvh_buffers_wide.wgsl", BVH_BUFFERS_WIDE_WGSL),
            BvhStorage::Textures => ("bvh_textures_wide.wgsl", BVH_TEXTURES_WIDE_WGSL),
        }
    }

    /// The WGSL file declaring this storage's triangle binding (binding 1) and
    /// `bvh_load_triangle`, shared by both layouts (for textures, with the texel addressing
    /// every BVH texture uses).
    pub fn triangles_wgsl(&self) -> (&'static str, &'static str) {
        match self {
            BvhStorage::Buffers => ("bvh_buffers_triangles.wgsl", BVH_BUFFERS_TRIANGLES_WGSL),
            BvhStorage::Textures => ("bvh_textures_triangles.wgsl", BVH_TEXTURES_TRIANGLES_WGSL),
        }
    }
}

/// Texels per row of the [`BvhStorage::Textures`] textures (`BVH_TEXEL_ROW_MASK + 1` in
/// `bvh_textures_triangles.wgsl`; 8192 is WebGPU's guaranteed `max_texture_dimension_2d`).
pub const TEXEL_ROW: u32 = 8192;

/// `bvh_buffers.wgsl`.
const BVH_BUFFERS_WGSL: &str = include_str!("../shaders/bvh_buffers.wgsl");
/// `bvh_textures.wgsl`.
const BVH_TEXTURES_WGSL: &str = include_str!("../shaders/bvh_textures.wgsl");
/// `bvh_buffers_triangles.wgsl`: the triangles' buffer, read by both layouts in buffers.
const BVH_BUFFERS_TRIANGLES_WGSL: &str = include_str!("../shaders/bvh_buffers_triangles.wgsl");
/// `bvh_textures_triangles.wgsl`: the triangles' texture and the texel addressing, read by
/// both layouts in textures.
const BVH_TEXTURES_TRIANGLES_WGSL: &str = include_str!("../shaders/bvh_textures_triangles.wgsl");
/// `bvh_buffers_wide.wgsl`: the wide layout's nodes in a buffer.
const BVH_BUFFERS_WIDE_WGSL: &str = include_str!("../shaders/bvh_buffers_wide.wgsl");
/// `bvh_textures_wide.wgsl`: the wide layout's nodes in a texture, five texels each.
const BVH_TEXTURES_WIDE_WGSL: &str = include_str!("../shaders/bvh_textures_wide.wgsl");

/// The storage-independent WGSL files, in composition order, as `(file name, source)`.
/// The BVH bindings ([`BvhStorage::wgsl`]) go after `types.wgsl`.
pub const SHADER_FILES: &[(&str, &str)] = &[
    ("types.wgsl", include_str!("../shaders/types.wgsl")),
    ("ray.wgsl", include_str!("../shaders/ray.wgsl")),
    ("surface.wgsl", include_str!("../shaders/surface.wgsl")),
    ("box.wgsl", include_str!("../shaders/box.wgsl")),
    (
        "triangle_hit.wgsl",
        include_str!("../shaders/triangle_hit.wgsl"),
    ),
    ("triangle.wgsl", TRIANGLE_WGSL),
    (
        "traverse_common.wgsl",
        include_str!("../shaders/traverse_common.wgsl"),
    ),
    (
        "traverse_instances.wgsl",
        include_str!("../shaders/traverse_instances.wgsl"),
    ),
    (
        "traverse_stack.wgsl",
        include_str!("../shaders/traverse_stack.wgsl"),
    ),
    (
        "traverse_full_stack.wgsl",
        include_str!("../shaders/traverse_full_stack.wgsl"),
    ),
    (
        "traverse_short_stack.wgsl",
        include_str!("../shaders/traverse_short_stack.wgsl"),
    ),
];

/// What every entry point shares (`entry.wgsl`: the override constants, `ray_index`); the
/// rays and hits bindings are [`RayInput::wgsl`]'s, the entry points themselves
/// `entry_walk.wgsl` specialised per walk ([`ModuleSet::files`](crate::key::ModuleSet::files)).
pub(crate) const ENTRY_WGSL: &str = include_str!("../shaders/entry.wgsl");

/// Entries of the full-stack kernel's stack (`FULL_STACK_SIZE` in
/// `traverse_full_stack.wgsl`): the deepest tree the full-stack traversal accepts.
pub const FULL_STACK_SIZE: u32 = 64;

/// Node groups (a node and its mask: two stack entries) the wide walk's stack holds per
/// lane (`WIDE_STACK_GROUPS` in `traverse_wide.wgsl`): a wide tree of at most this many
/// plus one levels never fills it; on a deeper one a ray that would overflow it comes back
/// incomplete and is finished on the CPU ([`crate::finish_incomplete`]).
pub const WIDE_STACK_GROUPS: u32 = FULL_STACK_SIZE / 2;

/// True when the wide walk's stack can overflow on a wide tree `depth` levels deep
/// (`WideBvh::depth`): the backends then keep a host copy to finish such rays.
pub fn wide_stack_may_overflow(depth: u32) -> bool {
    depth > WIDE_STACK_GROUPS + 1
}

/// Lanes per workgroup the traversal stacks are laid out for (`STACK_LANES` in
/// `traverse_stack.wgsl`): a shader that calls `trace_full_stack` or `trace_short_stack`
/// runs workgroups of at most this many invocations and passes `local_invocation_index`
/// as `lane`.
pub const STACK_LANES: u32 = 64;

/// Invocations per workgroup of the entry points (`WORKGROUP_SIZE` in `entry.wgsl`).
pub const WORKGROUP_SIZE: u32 = 64;

/// Group of the BVH bindings in [`kernel_source`].
pub const BVH_GROUP: u32 = 0;
/// Group of the ray batch bindings (`rays`, `hits`, `counters`) in [`kernel_source`].
pub const BATCH_GROUP: u32 = 1;

/// `triangle.wgsl`: the watertight f32 test, [`Precision::WatertightF32`] (the default).
const TRIANGLE_WGSL: &str = include_str!("../shaders/triangle.wgsl");
/// `triangle_moller_trumbore.wgsl`.
const TRIANGLE_MOLLER_TRUMBORE_WGSL: &str =
    include_str!("../shaders/triangle_moller_trumbore.wgsl");
/// `triangle_f64.wgsl` (needs `wgpu::Features::SHADER_F64`).
const TRIANGLE_F64_WGSL: &str = include_str!("../shaders/triangle_f64.wgsl");

/// The triangle module composed for `precision`, as `(file name, source)`: it takes
/// `triangle.wgsl`'s place in [`SHADER_FILES`] and defines the same
/// `intersect_triangle(r: PreparedRay, v0, v1, v2) -> TriHit`, so the traversal code is
/// shared by every precision.
pub fn triangle_wgsl(precision: Precision) -> (&'static str, &'static str) {
    match precision {
        Precision::WatertightF32 => ("triangle.wgsl", TRIANGLE_WGSL),
        Precision::MollerTrumboreF32 => (
            "triangle_moller_trumbore.wgsl",
            TRIANGLE_MOLLER_TRUMBORE_WGSL,
        ),
        Precision::WatertightF64 => ("triangle_f64.wgsl", TRIANGLE_F64_WGSL),
    }
}

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
    /// The walk `bvh_trace_closest` and `bvh_trace_any` take: [`Traversal::Wide`] reads
    /// the wide layout, the others the binary one (the stackless and short-stack walks its
    /// escape links too). A short stack's size is clamped to `1..=32`.
    pub traversal: Traversal,
    /// The triangle test ([`triangle_wgsl`]).
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
    pub fn module_set(&self) -> crate::key::ModuleSet {
        use crate::key::{Entries, ModuleSet};
        let base = match self.traversal {
            Traversal::Wide => ModuleSet::wide_in(self.storage, self.precision, Entries::None),
            t => ModuleSet {
                escapes: t.needs_escapes(),
                full_stack: !t.needs_escapes(),
                short_stack: t.needs_escapes(),
                ..ModuleSet::everything(self.storage, self.precision, Entries::None)
            },
        };
        ModuleSet {
            instances: self.instanced,
            masks: self.masks,
            filter: self.filter,
            ..base
        }
    }

    /// The call of its walk on `ray` and `lane`, any hit or closest.
    fn walk_call(&self, any_hit: bool) -> String {
        match self.traversal {
            Traversal::FullStack => format!("bvh_trace_full_stack(ray, {any_hit}, lane)"),
            Traversal::Stackless => format!("bvh_trace_short_stack(ray, {any_hit}, 0u, lane)"),
            Traversal::ShortStack(k) => {
                let k = k.clamp(1, bvhtrace_core::traverse::MAX_SHORT_STACK);
                format!("bvh_trace_short_stack(ray, {any_hit}, {k}u, lane)")
            }
            Traversal::Wide => format!("bvh_trace_wide(ray, {any_hit}, lane)"),
        }
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
        )
    }
}

/// `library.wgsl`: `bvh_trace_closest`, `bvh_trace_any` and the hit helpers.
const LIBRARY_WGSL: &str = include_str!("../shaders/library.wgsl");

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
///   memory, `bvh_lane_stacks`, one per lane, for workgroups of at most [`STACK_LANES`]
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
///   CPU with the same options (`bvhtrace_kernels::finish_incomplete`). Set it only for a
///   CPU driver, which ends invocations that loop too long
///   ([`crate::CPU_DRIVER_TRIP_LIMIT`]); on GPUs no ray is ever incomplete. The wide walk
///   returns it too on a wide tree deeper than [`WIDE_STACK_GROUPS`]` + 1` levels.
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
/// use bvhtrace_kernels::{BvhStorage, LibraryShape, Traversal};
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
/// let library = bvhtrace_kernels::wgsl_library(shape, 0);
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
            crate::ray_query::compose(
                &crate::ray_query::files(shape.instanced, shape.masks),
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
        &LIBRARY_WGSL
            .replace("BVH_LIBRARY_CLOSEST", &closest)
            .replace("BVH_LIBRARY_ANY", &any),
    );
    BvhLibrary {
        shape,
        group: bvh_group,
        source,
    }
}

/// The everything-on kernel module for `storage`: both binary walks with the BVH in group
/// [`BVH_GROUP`], and every entry point of the binary walks (`entry.wgsl`,
/// `entry_counters.wgsl` and `entry_walk.wgsl` four times; group [`BATCH_GROUP`]: `rays`,
/// `hits`, `counters`), so any [`crate::KernelKey::entry_point`] of a binary walk is in it
/// (the wide walk's are in its own module, [`crate::KernelKey::source`]). The pipelines
/// `GpuContext` (bvhtrace-gpu) builds use the specialised module of their key instead
/// ([`crate::KernelKey::source`]) unless it asks for every module (the `bench-hooks`
/// feature's `Composition::EverythingOn`).
pub fn kernel_source(storage: BvhStorage) -> String {
    kernel_source_for(storage, Precision::WatertightF32)
}

/// [`kernel_source`] with the triangle test of `precision` ([`triangle_wgsl`]).
pub fn kernel_source_for(storage: BvhStorage, precision: Precision) -> String {
    crate::key::ModuleSet::everything(storage, precision, crate::key::Entries::All)
        .compose(BVH_GROUP)
}

/// `entry_rays_buffer.wgsl`: the rays and hits in storage buffers.
const ENTRY_RAYS_BUFFER_WGSL: &str = include_str!("../shaders/entry_rays_buffer.wgsl");
/// `entry_rays_texture.wgsl`: the rays and hits in storage textures.
const ENTRY_RAYS_TEXTURE_WGSL: &str = include_str!("../shaders/entry_rays_texture.wgsl");

/// Where an entry point reads the batch's rays and writes its hits (bindings 0 and 1 of
/// group [`BATCH_GROUP`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum RayInput {
    /// Storage buffers of [`bvhtrace_core::Ray`]s (`rays`) and [`bvhtrace_core::Hit`]s
    /// (`hits`): what `GpuBvh::record` (bvhtrace-gpu) traces, and `GpuBvh::trace` (bvhtrace-gpu) with
    /// [`BvhStorage::Buffers`].
    #[default]
    Buffer,
    /// `Rgba32Uint` storage textures, [`TEXEL_ROW`] texels wide: the rays read-only, two
    /// texels per ray (`ray_texels`), the hits write-only, one texel per hit
    /// (`hit_texels`; `entry_rays_texture.wgsl`). What `GpuBvh::trace` (bvhtrace-gpu) uses with
    /// [`BvhStorage::Textures`], the layout for CPU drivers, where a texel access is one
    /// vector gather or one loop over the lanes and a buffer access a loop over the lanes
    /// per 32-bit word.
    Texture,
}

impl RayInput {
    /// What `GpuBvh::trace` (bvhtrace-gpu) uses with the BVH in `storage`: a texture with
    /// textures (CPU drivers), a buffer with buffers.
    pub fn for_storage(storage: BvhStorage) -> RayInput {
        match storage {
            BvhStorage::Textures => RayInput::Texture,
            BvhStorage::Buffers => RayInput::Buffer,
        }
    }

    /// The WGSL file declaring this input's two bindings, `load_ray`, `store_hit` and
    /// `batch_len`.
    pub fn wgsl(&self) -> (&'static str, &'static str) {
        match self {
            RayInput::Buffer => ("entry_rays_buffer.wgsl", ENTRY_RAYS_BUFFER_WGSL),
            RayInput::Texture => ("entry_rays_texture.wgsl", ENTRY_RAYS_TEXTURE_WGSL),
        }
    }
}
