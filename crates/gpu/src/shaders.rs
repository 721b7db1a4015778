//! The WGSL kernels: composed at load time from the files in the repository's `shaders/`
//! folder, one file per concern, and specialised per pipeline with override constants.
//!
//! | file | concern | CPU twin |
//! |---|---|---|
//! | `types.wgsl` | `Node`, `Triangle`, `Ray`, `Hit`, `Counters` | `bvhtrace_core::{FlatNode, FlatTriangle, Ray, Hit, Counters}` |
//! | `bvh_buffers.wgsl` or `bvh_textures.wgsl` | the BVH's bindings (group 0 by default) and fetch functions ([`BvhStorage`]) | `FlatBvh` |
//! | `ray.wgsl` | validity, `safe_inverse`, `prepare_ray` | `Ray::is_valid`, `PreparedRay::new` |
//! | `box.wgsl` | conservative slab test | `intersect::intersect_box` |
//! | `triangle_hit.wgsl` | `TriHit`, what every triangle test returns | `intersect::TriHit` |
//! | `triangle.wgsl` (or a [`Precision`] variant, [`triangle_wgsl`]) | watertight triangle test | `intersect::intersect_triangle` |
//! | `traverse_common.wgsl` | hit rule, leaf visit | `traverse::visit_leaf` |
//! | `traverse_stack.wgsl` | the per-lane stacks in workgroup memory, only for the full and short stack | `Vec` / the ring of `traverse::short_stack` |
//! | `traverse_full_stack.wgsl` | `trace_full_stack(ray, any_hit, lane)` | `traverse::full_stack` |
//! | `traverse_short_stack.wgsl` | `trace_short_stack(ray, any_hit, k, lane)` (k = 0: stackless) | `traverse::short_stack` |
//! | `bvh_buffers_escapes.wgsl` or `bvh_textures_escapes.wgsl` | the escape links (binding 2), only for the walks that read them | `FlatBvh::escapes` |
//! | `attribute_normals.wgsl` | per-vertex normals, only when the scene has them and the job uses them | - |
//! | `entry.wgsl` | what the entry points share: the overrides, `ray_index` | `traverse::trace_batch` |
//! | `entry_rays_buffer.wgsl` or `entry_rays_texture.wgsl` | where the rays come from and the hits go (`load_ray`, `store_hit`, `batch_len`; [`RayInput`]) | - |
//! | `entry_counters.wgsl` | the `counters` binding, only when counters are on | `trace_batch_counted` |
//! | `entry_{full,short}_stack[_counted].wgsl` | one entry point each | |
//!
//! [`wgsl_library`] concatenates the traversal library (every traversal, no entry point)
//! for use from your own shaders; [`kernel_source`] adds every entry point (the
//! everything-on module); [`KernelVariant::source`] and [`crate::PipelineFeatures`] compose
//! only what one pipeline needs. The BVH storage is chosen by which bindings file is
//! composed in. Nothing is copied between variants: the stackless walk is the short-stack
//! function with `k = 0`, the query and `k` are pipeline-overridable constants (`ANY_HIT`,
//! `SHORT_STACK_SIZE`), and counters are written only by the `*_counted` entry points.

use bvhtrace_core::Precision;

/// Where the kernels read the BVH from. Both give bit-identical results.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum BvhStorage {
    /// Storage buffers in the exact layout of [`bvhtrace_core::flat`]
    /// (`bvh_buffers.wgsl`): the portable choice, and the one to bind from your own
    /// shaders when you already hold the buffers.
    Buffers,
    /// `Rgba32Uint`/`R32Uint` textures of [`TEXEL_ROW`] texels per row
    /// (`bvh_textures.wgsl`). On lavapipe a texel fetch is a vector gather while a
    /// storage-buffer load is a per-lane scalar loop: traversal is about 2.5x faster.
    Textures,
}

impl BvhStorage {
    /// The storage [`crate::UploadOptions`] picks by default on an adapter of this type:
    /// textures on CPU drivers (lavapipe), buffers elsewhere.
    pub fn default_for(device_type: wgpu::DeviceType) -> Self {
        if device_type == wgpu::DeviceType::Cpu {
            BvhStorage::Textures
        } else {
            BvhStorage::Buffers
        }
    }

    /// The WGSL file declaring this storage's bindings and fetch functions.
    pub fn wgsl(&self) -> (&'static str, &'static str) {
        match self {
            BvhStorage::Buffers => ("bvh_buffers.wgsl", BVH_BUFFERS_WGSL),
            BvhStorage::Textures => ("bvh_textures.wgsl", BVH_TEXTURES_WGSL),
        }
    }
}

/// Texels per row of the [`BvhStorage::Textures`] textures (`BVH_TEXEL_ROW_MASK + 1` in
/// `bvh_textures.wgsl`; 8192 is WebGPU's guaranteed `max_texture_dimension_2d`).
pub const TEXEL_ROW: u32 = 8192;

/// `bvh_buffers.wgsl`.
pub const BVH_BUFFERS_WGSL: &str = include_str!("../../../shaders/bvh_buffers.wgsl");
/// `bvh_textures.wgsl`.
pub const BVH_TEXTURES_WGSL: &str = include_str!("../../../shaders/bvh_textures.wgsl");

/// The storage-independent WGSL files, in composition order, as `(file name, source)`.
/// The BVH bindings ([`BvhStorage::wgsl`]) go after `types.wgsl`.
pub const SHADER_FILES: &[(&str, &str)] = &[
    ("types.wgsl", include_str!("../../../shaders/types.wgsl")),
    ("ray.wgsl", include_str!("../../../shaders/ray.wgsl")),
    ("box.wgsl", include_str!("../../../shaders/box.wgsl")),
    (
        "triangle_hit.wgsl",
        include_str!("../../../shaders/triangle_hit.wgsl"),
    ),
    ("triangle.wgsl", TRIANGLE_WGSL),
    (
        "traverse_common.wgsl",
        include_str!("../../../shaders/traverse_common.wgsl"),
    ),
    (
        "traverse_stack.wgsl",
        include_str!("../../../shaders/traverse_stack.wgsl"),
    ),
    (
        "traverse_full_stack.wgsl",
        include_str!("../../../shaders/traverse_full_stack.wgsl"),
    ),
    (
        "traverse_short_stack.wgsl",
        include_str!("../../../shaders/traverse_short_stack.wgsl"),
    ),
];

/// What every entry point shares (`entry.wgsl`: the override constants, `ray_index`); the
/// rays and hits bindings are [`RayInput::wgsl`]'s, the entry points themselves
/// [`crate::features::ENTRY_POINT_FILES`].
pub const ENTRY_WGSL: &str = include_str!("../../../shaders/entry.wgsl");

/// Entries of the full-stack kernel's stack (`FULL_STACK_SIZE` in
/// `traverse_full_stack.wgsl`): the deepest tree the full-stack traversal accepts.
pub const FULL_STACK_SIZE: u32 = 64;

/// Lanes per workgroup the traversal stacks are laid out for (`STACK_LANES` in
/// `traverse_stack.wgsl`): a shader that calls `trace_full_stack` or `trace_short_stack`
/// runs workgroups of at most this many invocations and passes `local_invocation_index`
/// as `lane`.
pub const STACK_LANES: u32 = 64;

/// The trip budget ([`trip_limit_for`]) on CPU drivers: lavapipe ends every loop of an
/// invocation after 65,535 trips in all, counted per batch of 8 lanes over all its loops.
/// A ray's trips (box tests, triangle tests) are at most this budget. The count goes up
/// when a loop goes round again (not on entry), so only when some lane runs its next trip.
/// That trip spends one of the lane's trips (or ends the lane, once): a box test for the
/// inner loop, and for a walk's outer loop or the short stack's restart loop, the first box
/// test of the inner loop they enter; or, for a leaf's triangle loop, a triangle test or
/// the end of the leaf, at most once per entry, which is once per outer trip. So a batch
/// counts at most `8 * budget + 8` for the first kind and `8 * budget + 1` for leaf ends:
/// `16 * 3,800 + 9 = 60,809`.
pub const CPU_DRIVER_TRIP_LIMIT: u32 = 3_800;

/// The `TRIP_LIMIT` override for an adapter: [`CPU_DRIVER_TRIP_LIMIT`] on CPU drivers
/// (lavapipe), unbounded (`u32::MAX`) elsewhere. A ray that spends it comes back as
/// [`bvhtrace_core::INCOMPLETE`] instead of a silently truncated answer.
pub fn trip_limit_for(info: &wgpu::AdapterInfo) -> u32 {
    if info.device_type == wgpu::DeviceType::Cpu {
        CPU_DRIVER_TRIP_LIMIT
    } else {
        u32::MAX
    }
}

/// The `DISPATCH_THREADS` override for an adapter (`entry.wgsl`): on a CPU driver, the
/// worker threads it splits each dispatch among, as contiguous ranges of workgroups
/// (lavapipe: `LP_NUM_THREADS`, by default one per CPU); 1 elsewhere. The entry points
/// deal ray blocks out to those ranges in turn, so that each thread gets a share of every
/// part of a frame instead of one band of it.
pub fn dispatch_threads_for(info: &wgpu::AdapterInfo) -> u32 {
    let cpus = std::thread::available_parallelism().map_or(1, |n| n.get());
    dispatch_threads(
        info.device_type,
        std::env::var("LP_NUM_THREADS").ok().as_deref(),
        cpus,
    )
}

/// [`dispatch_threads_for`] given the `LP_NUM_THREADS` value and the CPU count: at least
/// 1 and at most [`MAX_DISPATCH_THREADS`].
pub fn dispatch_threads(
    device_type: wgpu::DeviceType,
    lp_num_threads: Option<&str>,
    cpus: usize,
) -> u32 {
    if device_type != wgpu::DeviceType::Cpu {
        return 1;
    }
    let threads = lp_num_threads
        .and_then(|v| v.trim().parse::<u32>().ok())
        .unwrap_or(u32::try_from(cpus).unwrap_or(u32::MAX));
    threads.clamp(1, MAX_DISPATCH_THREADS)
}

/// The most threads [`dispatch_threads`] assumes (lavapipe's own cap is lower).
pub const MAX_DISPATCH_THREADS: u32 = 64;

/// Invocations per workgroup of the entry points (`WORKGROUP_SIZE` in `entry.wgsl`).
pub const WORKGROUP_SIZE: u32 = 64;

/// Group of the BVH bindings in [`kernel_source`].
pub const BVH_GROUP: u32 = 0;
/// Group of the ray batch bindings (`rays`, `hits`, `counters`) in [`kernel_source`].
pub const BATCH_GROUP: u32 = 1;

/// `triangle.wgsl`: the watertight f32 test, [`Precision::WatertightF32`] (the default).
pub const TRIANGLE_WGSL: &str = include_str!("../../../shaders/triangle.wgsl");
/// `triangle_moller_trumbore.wgsl`.
pub const TRIANGLE_MOLLER_TRUMBORE_WGSL: &str =
    include_str!("../../../shaders/triangle_moller_trumbore.wgsl");
/// `triangle_f64.wgsl` (needs `wgpu::Features::SHADER_F64`).
pub const TRIANGLE_F64_WGSL: &str = include_str!("../../../shaders/triangle_f64.wgsl");

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

/// The traversal library without entry points, reading the BVH from `storage` bound at
/// `@group(bvh_group)`, bindings 0 (nodes), 1 (triangles) and 2 (escapes, read only by
/// `trace_short_stack`). Bind [`crate::GpuBvh::bind_group`] there, with
/// [`crate::GpuContext::bvh_layout`] in your pipeline layout.
///
/// It declares the structs `Node`, `Triangle`, `Ray`, `Hit`, `Counters`, `TraceResult` and
/// the functions
///
/// * `trace_full_stack(ray: Ray, any_hit: bool, lane: u32) -> TraceResult` (trees of depth
///   up to [`FULL_STACK_SIZE`]),
/// * `trace_short_stack(ray: Ray, any_hit: bool, k: u32, lane: u32) -> TraceResult`, where
///   `k` is the ring size (`1..=32`) or `0` for the stackless walk,
///
/// where `lane` is the invocation's `local_invocation_index`: the stacks live in workgroup
/// memory (`lane_stacks`, 16 KiB), one per lane, for workgroups of at most [`STACK_LANES`]
/// invocations. Create the pipeline with `zero_initialize_workgroup_memory: false`: the
/// walks write every entry before they read it, and zeroing 16 KiB per workgroup is wasted
/// time.
///
/// plus helpers whose names you must not reuse (`intersect_box`, `intersect_triangle`,
/// `prepare_ray`, `visit_leaf`, `load_node`, `fmin`, `fmax`, `component`, ...). Pass
/// constants for `any_hit` and `k` and the driver folds them away.
///
/// # Example
///
/// A shader that traces one ray per invocation with its own bindings in group 1:
///
/// ```
/// use bvhtrace_gpu::BvhStorage;
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
///     let ray = Ray(vec3<f32>(x, 0.0, 5.0), 0.0, vec3<f32>(0.0, 0.0, -1.0), 1e30);
///     let res = trace_short_stack(ray, false, 6u, lane); // closest hit, 6-entry short stack
///     ids[gid.x] = res.hit.prim;
/// }
/// "#;
/// let source = format!("{}\n{}", bvhtrace_gpu::wgsl_library(BvhStorage::Buffers, 0), my_shader);
/// # let module = naga::front::wgsl::parse_str(&source).expect("parses");
/// # naga::valid::Validator::new(Default::default(), naga::valid::Capabilities::all())
/// #     .validate(&module)
/// #     .expect("validates");
/// // let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
/// //     label: Some("my shader"),
/// //     source: wgpu::ShaderSource::Wgsl(source.into()),
/// // });
/// // Pipeline layout: [Some(ctx.bvh_layout(bvh.storage(), true)), Some(&my_group_1_layout)];
/// // pass.set_bind_group(0, bvh.bind_group(true), &[]);
/// ```
pub fn wgsl_library(storage: BvhStorage, bvh_group: u32) -> String {
    wgsl_library_for(storage, Precision::WatertightF32, bvh_group)
}

/// [`wgsl_library`] with the triangle test of `precision` ([`triangle_wgsl`]) in place of
/// `triangle.wgsl`. [`Precision::WatertightF64`] needs a device with
/// `wgpu::Features::SHADER_F64` (naga: `Capabilities::FLOAT64`).
pub fn wgsl_library_for(storage: BvhStorage, precision: Precision, bvh_group: u32) -> String {
    crate::features::ModuleSet::everything(storage, precision, crate::features::Entries::None)
        .compose(bvh_group)
}

/// The everything-on kernel module for `storage`: [`wgsl_library`] with the BVH in group
/// [`BVH_GROUP`], and every entry point (`entry.wgsl`, `entry_counters.wgsl` and the four
/// `entry_*.wgsl` files; group [`BATCH_GROUP`]: `rays`, `hits`, `counters`), so any
/// [`KernelVariant::entry_point`] is in it. The pipelines [`crate::GpuContext`] builds use
/// the specialised module of their variant instead ([`KernelVariant::source`],
/// [`crate::PipelineFeatures`]) unless it is set to [`crate::Composition::EverythingOn`].
pub fn kernel_source(storage: BvhStorage) -> String {
    kernel_source_for(storage, Precision::WatertightF32)
}

/// [`kernel_source`] with the triangle test of `precision` ([`wgsl_library_for`]).
pub fn kernel_source_for(storage: BvhStorage, precision: Precision) -> String {
    crate::features::ModuleSet::everything(storage, precision, crate::features::Entries::All)
        .compose(BVH_GROUP)
}

/// `entry_rays_buffer.wgsl`: the rays and hits in storage buffers.
pub const ENTRY_RAYS_BUFFER_WGSL: &str = include_str!("../../../shaders/entry_rays_buffer.wgsl");
/// `entry_rays_texture.wgsl`: the rays and hits in storage textures.
pub const ENTRY_RAYS_TEXTURE_WGSL: &str = include_str!("../../../shaders/entry_rays_texture.wgsl");

/// Where an entry point reads the batch's rays and writes its hits (bindings 0 and 1 of
/// group [`BATCH_GROUP`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum RayInput {
    /// Storage buffers of [`bvhtrace_core::Ray`]s (`rays`) and [`bvhtrace_core::Hit`]s
    /// (`hits`): what [`crate::GpuBvh::record`] traces, and [`crate::GpuBvh::trace`] with
    /// [`BvhStorage::Buffers`].
    #[default]
    Buffer,
    /// `Rgba32Uint` storage textures, [`TEXEL_ROW`] texels wide: the rays read-only, two
    /// texels per ray (`ray_texels`), the hits write-only, one texel per hit
    /// (`hit_texels`; `entry_rays_texture.wgsl`). What [`crate::GpuBvh::trace`] uses with
    /// [`BvhStorage::Textures`], the layout for CPU drivers, where a texel access is one
    /// vector gather or one loop over the lanes and a buffer access a loop over the lanes
    /// per 32-bit word.
    Texture,
}

impl RayInput {
    /// What [`crate::GpuBvh::trace`] uses with the BVH in `storage`: a texture with
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

/// Which entry point and which override values one pipeline uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct KernelVariant {
    /// Where the BVH is read from.
    pub storage: BvhStorage,
    /// Full stack (false) or short stack / stackless (true).
    pub short_stack: bool,
    /// `SHORT_STACK_SIZE` (0 = stackless); 0 and unused for the full stack.
    pub k: u32,
    /// `ANY_HIT`.
    pub any_hit: bool,
    /// The `*_counted` entry point.
    pub counters: bool,
    /// The triangle test composed into the module ([`triangle_wgsl`]).
    pub precision: Precision,
    /// Where the rays are read from.
    pub rays: RayInput,
    /// `PARALLEL_RAYS` (`box.wgsl`): some ray of the batch may have a zero direction
    /// component ([`bvhtrace_core::intersect::is_parallel_to_a_slab`]). True unless the
    /// batch is known to have none ([`KernelVariant::for_rays`]).
    pub parallel_rays: bool,
}

impl KernelVariant {
    /// The variant tracing `traversal` for `query`. `ShortStack(k)` is clamped to
    /// `1..=MAX_SHORT_STACK`, as the CPU twin does.
    pub fn new(
        storage: BvhStorage,
        traversal: bvhtrace_core::Traversal,
        query: bvhtrace_core::Query,
        counters: bool,
    ) -> Self {
        use bvhtrace_core::Traversal;
        use bvhtrace_core::traverse::MAX_SHORT_STACK;
        let (short_stack, k) = match traversal {
            Traversal::FullStack => (false, 0),
            Traversal::Stackless => (true, 0),
            Traversal::ShortStack(k) => (true, k.clamp(1, MAX_SHORT_STACK)),
        };
        KernelVariant {
            storage,
            short_stack,
            k,
            any_hit: query == bvhtrace_core::Query::Any,
            counters,
            precision: Precision::WatertightF32,
            rays: RayInput::Buffer,
            parallel_rays: true,
        }
    }

    /// The traversal this variant walks (the inverse of [`KernelVariant::new`]).
    pub fn traversal(&self) -> bvhtrace_core::Traversal {
        use bvhtrace_core::Traversal;
        match (self.short_stack, self.k) {
            (false, _) => Traversal::FullStack,
            (true, 0) => Traversal::Stackless,
            (true, k) => Traversal::ShortStack(k),
        }
    }

    /// The query this variant answers.
    pub fn query(&self) -> bvhtrace_core::Query {
        if self.any_hit {
            bvhtrace_core::Query::Any
        } else {
            bvhtrace_core::Query::Closest
        }
    }

    /// The same variant with the triangle test of `precision`.
    pub fn with_precision(self, precision: Precision) -> Self {
        KernelVariant { precision, ..self }
    }

    /// The same variant reading its rays from `rays`.
    pub fn with_rays(self, rays: RayInput) -> Self {
        KernelVariant { rays, ..self }
    }

    /// The same variant specialised for `rays`: the box test's parallel path is compiled
    /// out when none of them has a zero direction component.
    pub fn for_rays(self, rays: &[bvhtrace_core::Ray]) -> Self {
        let parallel_rays = rays
            .iter()
            .any(|r| bvhtrace_core::intersect::is_parallel_to_a_slab(glam::Vec3::from(r.dir)));
        KernelVariant {
            parallel_rays,
            ..self
        }
    }

    /// Every variant the tests validate for `storage`: each traversal kind (full stack,
    /// stackless, short stack with `k`) x query x counters.
    pub fn all_for_k(storage: BvhStorage, k: u32) -> Vec<KernelVariant> {
        let mut v = Vec::new();
        for (short_stack, kk) in [(false, 0), (true, 0), (true, k)] {
            for any_hit in [false, true] {
                for counters in [false, true] {
                    v.push(KernelVariant {
                        short_stack,
                        k: kk,
                        any_hit,
                        counters,
                        ..KernelVariant::new(
                            storage,
                            bvhtrace_core::Traversal::FullStack,
                            bvhtrace_core::Query::Closest,
                            false,
                        )
                    });
                }
            }
        }
        v
    }

    /// The entry point's name in [`kernel_source`].
    pub fn entry_point(&self) -> &'static str {
        match (self.short_stack, self.counters) {
            (false, false) => "trace_full_stack_main",
            (false, true) => "trace_full_stack_counted",
            (true, false) => "trace_short_stack_main",
            (true, true) => "trace_short_stack_counted",
        }
    }

    /// The override constants the entry point uses, as wgpu takes them.
    pub fn constants(&self) -> Vec<(&'static str, f64)> {
        let flag = |b: bool| if b { 1.0 } else { 0.0 };
        let mut c = vec![
            ("ANY_HIT", flag(self.any_hit)),
            ("PARALLEL_RAYS", flag(self.parallel_rays)),
        ];
        if self.short_stack {
            c.push(("SHORT_STACK_SIZE", f64::from(self.k)));
        }
        c
    }

    /// True when the kernel reads the escape links.
    pub fn needs_escapes(&self) -> bool {
        self.short_stack
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bvhtrace_core::{Query, Ray, Traversal};
    use glam::Vec3;

    #[test]
    fn dispatch_threads_follow_the_cpu_driver() {
        use wgpu::DeviceType::{Cpu, DiscreteGpu, IntegratedGpu};
        // GPUs hand out workgroups as they go: no interleave.
        assert_eq!(dispatch_threads(DiscreteGpu, Some("8"), 16), 1);
        assert_eq!(dispatch_threads(IntegratedGpu, None, 16), 1);
        // lavapipe: LP_NUM_THREADS, else one thread per CPU.
        assert_eq!(dispatch_threads(Cpu, None, 2), 2);
        assert_eq!(dispatch_threads(Cpu, Some("3"), 2), 3);
        assert_eq!(dispatch_threads(Cpu, Some(" 4 "), 2), 4);
        assert_eq!(dispatch_threads(Cpu, Some("lots"), 6), 6);
        // 0 threads: the dispatch runs on the calling thread, as one range.
        assert_eq!(dispatch_threads(Cpu, Some("0"), 2), 1);
        assert_eq!(dispatch_threads(Cpu, None, 0), 1);
        assert_eq!(
            dispatch_threads(Cpu, Some("100000"), 2),
            MAX_DISPATCH_THREADS
        );
    }

    #[test]
    fn the_parallel_path_is_left_out_only_without_zero_direction_components() {
        let v = KernelVariant::new(
            BvhStorage::Textures,
            Traversal::FullStack,
            Query::Closest,
            false,
        );
        assert!(v.parallel_rays, "unknown rays keep the parallel path");
        let ray = |d: Vec3| Ray::new(Vec3::ZERO, d);
        let oblique = [
            ray(Vec3::new(0.3, -0.2, 1.0)),
            ray(Vec3::new(-1.0, 1e-30, 2.0)),
        ];
        assert!(!v.for_rays(&oblique).parallel_rays);
        assert!(!v.for_rays(&[]).parallel_rays);
        for d in [
            Vec3::new(0.0, 0.5, 1.0),
            Vec3::new(0.5, -0.0, 1.0),
            // Subnormal: flushed to zero by the kernels, so parallel too.
            Vec3::new(0.5, 1.0, f32::from_bits(1)),
        ] {
            let mut rays = oblique.to_vec();
            rays.push(ray(d));
            let p = v.for_rays(&rays);
            assert!(p.parallel_rays, "{d:?}");
            assert!(p.constants().contains(&("PARALLEL_RAYS", 1.0)));
        }
        assert!(
            v.for_rays(&oblique)
                .constants()
                .contains(&("PARALLEL_RAYS", 0.0))
        );
    }
}
