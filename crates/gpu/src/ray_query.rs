//! The ray-query tracer: the tree's triangles handed to the device's own acceleration
//! structure builder (a BLAS per mesh, a TLAS over the instances) and traced by `rayQuery`
//! in a compute kernel ([`bvhtrace_engine::ray_query`]), behind the same [`Tracer`]
//! interface, ray and hit layout and ids as our walks.
//!
//! Where a device has ray-tracing hardware this is the fast path; on a CPU driver such as
//! Mesa 25's lavapipe our walks are faster (`docs/benchmarks.md`), and the front door's
//! automatic choice says so. The answers are not bit for bit our walks': the driver's
//! triangle test is its own. `tests/ray_query.rs` states and checks the rule.
//!
//! Alpha-tested geometry (`FlatBvh::masks`) is cut by our walks' own test
//! (`bvh_alpha_masks.wgsl`, its tables at binding 5): the masked meshes' BLASes are built
//! without the opaque flag, and the query loop confirms a candidate only when
//! `MaskTables::accept` would, at the barycentrics the driver gives the candidate. Those
//! are the driver's, not our triangle test's (they differ in the last bits: by at most
//! 2e-5 on lavapipe over the tests' scenes), so a candidate on a texel border may be cut on
//! one side and kept on the other. The rule adds one clause for a masked tree: where the
//! answers differ otherwise, the nearer of the two hits lies on a masked triangle whose
//! mask changes its verdict within 1e-3 (in barycentrics) of that hit's barycentrics, and
//! such rays are a sliver (the tests allow 1 in 200).

use std::collections::HashMap;
use std::sync::{Arc, Mutex};

use bvhtrace_core::flat::{FlatInstance, FlatNode};
use bvhtrace_core::masks::NO_MASKS;
use bvhtrace_core::{
    FlatBvh, Hit, InstanceTable, Precision, Query, Ray, TraceOptions, TraceOutput, TracePhases,
};
use bvhtrace_engine::BvhStorage;
use bvhtrace_engine::pages::{PAGE_BINDING_STRIDE, Pages, check_storage_buffers};
use bvhtrace_engine::plan::{
    DeviceLimits, HIT_BYTES, RAY_BYTES, check_buffer_size, plan_dispatches, rays_per_dispatch,
    submissions_in_flight,
};
use bvhtrace_engine::storage::RayInput;
use bvhtrace_engine::tracer::{check_update_shape, mesh_fingerprint, tree_shape};
use bvhtrace_engine::upload::{ArrayRole, DeviceArray};
use bvhtrace_engine::{BvhLibrary, LibraryShape, TraceError, Tracer, UploadStats, wgsl_library};
use web_time::Instant;
use wgpu::util::DeviceExt;

use crate::context::storage_entry;
use crate::trace::{binding, map_all, read_mapped};
use crate::{BvhBindGroup, GpuContext, GpuError, RAY_QUERY_BACKEND};

/// One mesh's triangles: a run of slots in the triangle buffer, and its BLAS.
struct Mesh {
    /// Its root in `FlatBvh::nodes` (0 for one mesh).
    root: u32,
    /// First triangle slot and count.
    first: u32,
    count: u32,
    /// No instance of it has alpha masks: its BLAS geometry is built opaque, so the driver
    /// commits its hits without handing them to the query loop.
    opaque: bool,
}

/// A tree handed to the device's acceleration structures, ready to trace with ray queries.
/// Needs a [`GpuContext`] created with [`crate::ContextOptions::ray_queries`] on an
/// adapter with wgpu's `EXPERIMENTAL_RAY_QUERY`.
pub struct RayQueryBvh {
    ctx: GpuContext,
    /// `FlatBvh::triangles`: the BLAS vertices (16-byte stride) and binding 1.
    triangles: wgpu::Buffer,
    /// How the triangles are bound: one binding, or pages of one binding each over the
    /// same buffer when they exceed the device's largest binding ([`Pages`]).
    pages: Pages,
    /// Binding 2 (two levels): each mesh's first triangle slot.
    mesh_firsts: Option<wgpu::Buffer>,
    /// Binding 4 (two levels): `FlatBvh::instances`.
    instances: Option<wgpu::Buffer>,
    /// Binding 5 (a masked BVH): `MaskTables::words`, instances in `FlatBvh::instances`'
    /// order (the TLAS's).
    masks: Option<wgpu::Buffer>,
    meshes: Vec<Mesh>,
    /// Each instance's mesh (index into `meshes`); one entry for one mesh.
    instance_mesh: Vec<u32>,
    blases: Vec<wgpu::Blas>,
    tlas: wgpu::Tlas,
    layout: wgpu::BindGroupLayout,
    /// The BVH group, made once the acceleration structures are built.
    group: Option<wgpu::BindGroup>,
    /// Pipelines by (any hit, ray mask).
    pipelines: Mutex<HashMap<(bool, u8), wgpu::ComputePipeline>>,
    shape: (usize, usize, usize, u32),
    fingerprint: u64,
    table: Option<Arc<InstanceTable>>,
    stats: UploadStats,
    /// Wall time of the last acceleration-structure build (or update), milliseconds.
    build_ms: f64,
    /// The ray batches' buffers kept between traces, one per submission in flight; only
    /// with submissions in flight (a GPU's tuning): docs/gpu-wall.md says why not on a
    /// CPU driver.
    scratch: Mutex<Vec<RayQueryScratch>>,
}

/// The buffers of a ray-query submission: `capacity` rays, their hits, and the hits'
/// readback.
struct RayQueryScratch {
    capacity: u64,
    rays: wgpu::Buffer,
    hits: wgpu::Buffer,
    read: wgpu::Buffer,
}

/// A ray-query submission not yet read back: on scratch `slot`, `count` rays.
struct InFlight {
    slot: usize,
    index: wgpu::SubmissionIndex,
    count: u64,
    started: Instant,
    submitted: Instant,
}

impl RayQueryScratch {
    fn new(device: &wgpu::Device, capacity: u64) -> RayQueryScratch {
        use wgpu::BufferUsages as U;
        let buffer = |label, bytes, usage| {
            device.create_buffer(&wgpu::BufferDescriptor {
                label: Some(label),
                size: bytes,
                usage,
                mapped_at_creation: false,
            })
        };
        RayQueryScratch {
            capacity,
            rays: buffer(
                "bvhtrace ray-query rays",
                capacity * RAY_BYTES,
                U::STORAGE | U::COPY_DST,
            ),
            hits: buffer(
                "bvhtrace ray-query hits",
                capacity * HIT_BYTES,
                U::STORAGE | U::COPY_SRC,
            ),
            read: buffer(
                "bvhtrace ray-query readback",
                capacity * HIT_BYTES,
                U::MAP_READ | U::COPY_DST,
            ),
        }
    }
}

impl std::fmt::Debug for RayQueryBvh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RayQueryBvh")
            .field("meshes", &self.meshes.len())
            .field("instances", &self.instance_mesh.len())
            .field("build_ms", &self.build_ms)
            .finish_non_exhaustive()
    }
}

/// The triangle slots under `root`: a subtree's leaves hold one contiguous run.
fn mesh_range(nodes: &[FlatNode], root: u32) -> Result<(u32, u32), TraceError> {
    let bad = |problem: String| TraceError::BadBuffer {
        buffer: "nodes",
        problem,
    };
    let (mut lo, mut hi, mut leaves) = (u32::MAX, 0u32, 0u64);
    let mut stack = vec![root];
    while let Some(i) = stack.pop() {
        let n = nodes
            .get(i as usize)
            .ok_or_else(|| bad(format!("node {i} is past the {} nodes", nodes.len())))?;
        if n.is_leaf() {
            lo = lo.min(n.right_or_first);
            hi = hi.max(n.right_or_first + n.count());
            leaves += u64::from(n.count());
        } else {
            stack.push(i + 1);
            stack.push(n.right_or_first);
        }
    }
    if leaves != u64::from(hi.saturating_sub(lo)) {
        return Err(bad(format!(
            "the mesh at node {root} does not hold one run of triangles"
        )));
    }
    Ok((lo, hi - lo))
}

/// The object-to-world transform (three rows of a 3x4 matrix, as a TLAS instance takes
/// it) of an instance whose `world_to_object` is given, inverted in f64.
fn object_to_world(inst: &FlatInstance, index: usize) -> Result<[f32; 12], TraceError> {
    let m = inst.world_to_object.map(|r| r.map(f64::from));
    let a = |r: usize, c: usize| m[r][c];
    let det = a(0, 0) * (a(1, 1) * a(2, 2) - a(1, 2) * a(2, 1))
        - a(0, 1) * (a(1, 0) * a(2, 2) - a(1, 2) * a(2, 0))
        + a(0, 2) * (a(1, 0) * a(2, 1) - a(1, 1) * a(2, 0));
    if !(det.is_finite() && det != 0.0) {
        return Err(TraceError::BadBuffer {
            buffer: "instances",
            problem: format!("instance {index}'s transform cannot be inverted (determinant {det})"),
        });
    }
    // The inverse of the 3x3 part by cofactors, then the translation moved across.
    let cof = |r: usize, c: usize| {
        let (r0, r1) = ((r + 1) % 3, (r + 2) % 3);
        let (c0, c1) = ((c + 1) % 3, (c + 2) % 3);
        a(r0, c0) * a(r1, c1) - a(r0, c1) * a(r1, c0)
    };
    let mut inv = [[0.0f64; 3]; 3];
    for (r, row) in inv.iter_mut().enumerate() {
        for (c, x) in row.iter_mut().enumerate() {
            *x = cof(c, r) / det;
        }
    }
    let t = [a(0, 3), a(1, 3), a(2, 3)];
    let mut out = [0.0f32; 12];
    for r in 0..3 {
        for c in 0..3 {
            out[r * 4 + c] = inv[r][c] as f32;
        }
        out[r * 4 + 3] = -(inv[r][0] * t[0] + inv[r][1] * t[1] + inv[r][2] * t[2]) as f32;
    }
    Ok(out)
}

impl RayQueryBvh {
    /// Hands `bvh` (one mesh or two levels) to the device's acceleration structures: its
    /// triangles uploaded once, in leaf order (a spatial order, which the drivers' builders
    /// are fastest on), a BLAS per mesh over them, a TLAS over the instances (their
    /// transforms inverted, masks and mesh as custom data). The build is waited for, and
    /// timed ([`RayQueryBvh::build_ms`]). A masked BVH's tables go with it (binding 5,
    /// `UploadStats::masks_bytes`), and the BLASes of its masked meshes are built without
    /// the opaque flag, so that the kernel tests their candidates (see the [module
    /// documentation](self) for the rule that holds there).
    ///
    /// [`TraceError::MissingFeature`] when the device lacks `EXPERIMENTAL_RAY_QUERY`; a
    /// limit error when the triangles exceed a buffer or the masks a storage binding.
    /// Triangles over one binding are bound in pages of one binding each, ranges of the
    /// one buffer the BLASes read.
    pub fn upload(ctx: &GpuContext, bvh: &FlatBvh) -> Result<RayQueryBvh, GpuError> {
        if !ctx.has_ray_queries() {
            return Err(TraceError::MissingFeature {
                feature: "EXPERIMENTAL_RAY_QUERY",
                needed_for: "the ray-query tracer",
                adapter: ctx.adapter_info().name.clone(),
            });
        }
        if bvh.triangles().is_empty() {
            return Err(TraceError::EmptyBvh);
        }
        let start = Instant::now();
        let tri_bytes: &[u8] = bytemuck::cast_slice(bvh.triangles());
        let pages = triangle_pages(ctx, tri_bytes)?;
        let mask_words = masks_words(bvh);
        if let Some(w) = &mask_words {
            check_buffer_size(ctx.limits(), "alpha masks", 4 * w.len() as u64)?;
        }
        let instanced = bvh.is_instanced();
        let (meshes, instance_mesh) = meshes_of(bvh)?;
        // wgpu counts an unindexed BLAS's vertices against its primitive limit.
        let most = u64::from(ctx.device().limits().max_blas_primitive_count);
        if let Some(m) = meshes.iter().find(|m| 3 * u64::from(m.count) > most) {
            return Err(TraceError::Unsupported {
                backend: RAY_QUERY_BACKEND,
                what: format!(
                    "a mesh of {} triangles: the device's max_blas_primitive_count ({most}) \
                     counts its {} vertices (unindexed); trace it with our walks, or as \
                     instances of smaller meshes",
                    m.count,
                    3 * u64::from(m.count)
                ),
            });
        }
        let device = ctx.device();
        let made = ctx.scoped("building the acceleration structures", || {
            let triangles = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                label: Some("bvhtrace ray-query triangles"),
                contents: tri_bytes,
                usage: wgpu::BufferUsages::STORAGE
                    | wgpu::BufferUsages::BLAS_INPUT
                    | wgpu::BufferUsages::COPY_DST,
            });
            let blases: Vec<wgpu::Blas> = meshes
                .iter()
                .map(|m| {
                    device.create_blas(
                        &wgpu::CreateBlasDescriptor {
                            label: Some("bvhtrace mesh"),
                            flags: wgpu::AccelerationStructureFlags::PREFER_FAST_TRACE
                                | wgpu::AccelerationStructureFlags::ALLOW_UPDATE,
                            update_mode: wgpu::AccelerationStructureUpdateMode::PreferUpdate,
                        },
                        wgpu::BlasGeometrySizeDescriptors::Triangles {
                            descriptors: vec![blas_size(m)],
                        },
                    )
                })
                .collect();
            let tlas = device.create_tlas(&wgpu::CreateTlasDescriptor {
                label: Some("bvhtrace instances"),
                max_instances: instance_mesh.len() as u32,
                flags: wgpu::AccelerationStructureFlags::PREFER_FAST_TRACE,
                update_mode: wgpu::AccelerationStructureUpdateMode::Build,
            });
            let mesh_firsts = instanced.then(|| {
                let firsts: Vec<u32> = meshes.iter().map(|m| m.first).collect();
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("bvhtrace ray-query mesh firsts"),
                    contents: bytemuck::cast_slice(&firsts),
                    usage: wgpu::BufferUsages::STORAGE,
                })
            });
            let instances = instanced.then(|| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("bvhtrace ray-query instances"),
                    contents: bytemuck::cast_slice(bvh.instances()),
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                })
            });
            let masks = mask_words.as_ref().map(|w| {
                device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
                    label: Some("bvhtrace ray-query alpha masks"),
                    contents: bytemuck::cast_slice(w),
                    usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST,
                })
            });
            (triangles, blases, tlas, mesh_firsts, instances, masks)
        })?;
        let (triangles, blases, tlas, mesh_firsts, instances, masks) = made;
        let layout = group_layout(device, instanced, masks.is_some(), pages);
        let mut rq = RayQueryBvh {
            ctx: ctx.clone(),
            group: None,
            triangles,
            pages,
            mesh_firsts,
            instances,
            masks,
            meshes,
            instance_mesh,
            blases,
            tlas,
            layout,
            pipelines: Mutex::new(HashMap::new()),
            shape: tree_shape(bvh),
            fingerprint: mesh_fingerprint(bvh),
            table: InstanceTable::of(bvh),
            stats: UploadStats {
                storage: bvhtrace_engine::BvhStorage::Buffers,
                nodes_bytes: 0,
                triangles_bytes: tri_bytes.len() as u64,
                escapes_bytes: 0,
                instances_bytes: std::mem::size_of_val(bvh.instances()) as u64,
                masks_bytes: mask_words.map_or(0, |w| 4 * w.len() as u64),
                upload_ms: 0.0,
            },
            build_ms: 0.0,
            scratch: Mutex::new(Vec::new()),
        };
        rq.set_instances(bvh)?;
        rq.build(true)?;
        rq.group = Some(rq.make_group()?);
        rq.stats.upload_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(rq)
    }

    /// The bind group of binding 0 (the TLAS), 1, for two levels 2 and 4, and for a masked
    /// BVH 5.
    fn make_group(&self) -> Result<wgpu::BindGroup, GpuError> {
        let mut entries = vec![wgpu::BindGroupEntry {
            binding: 0,
            resource: self.tlas.as_binding(),
        }];
        let total = self.triangles.size();
        let page = match self.pages.is_one() {
            true => total,
            false => self.pages.per_page(TRIANGLE_BYTES) * TRIANGLE_BYTES,
        };
        for p in 0..u64::from(self.pages.triangles) {
            let offset = p * page;
            entries.push(wgpu::BindGroupEntry {
                binding: 1 + PAGE_BINDING_STRIDE * p as u32,
                resource: wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                    buffer: &self.triangles,
                    offset,
                    size: std::num::NonZeroU64::new(page.min(total - offset)),
                }),
            });
        }
        if let (Some(f), Some(i)) = (&self.mesh_firsts, &self.instances) {
            entries.push(wgpu::BindGroupEntry {
                binding: 2,
                resource: f.as_entire_binding(),
            });
            entries.push(wgpu::BindGroupEntry {
                binding: 4,
                resource: i.as_entire_binding(),
            });
        }
        if let Some(m) = &self.masks {
            entries.push(wgpu::BindGroupEntry {
                binding: 5,
                resource: m.as_entire_binding(),
            });
        }
        self.ctx.scoped("binding the acceleration structure", || {
            self.ctx
                .device()
                .create_bind_group(&wgpu::BindGroupDescriptor {
                    label: Some("bvhtrace ray-query bvh"),
                    layout: &self.layout,
                    entries: &entries,
                })
        })
    }

    /// Fills the TLAS's instances from `bvh`'s (one identity instance for one mesh).
    fn set_instances(&mut self, bvh: &FlatBvh) -> Result<(), GpuError> {
        const IDENTITY: [f32; 12] = [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        if !bvh.is_instanced() {
            self.tlas[0] = Some(wgpu::TlasInstance::new(&self.blases[0], IDENTITY, 0, 0xff));
            return Ok(());
        }
        for (i, inst) in bvh.instances().iter().enumerate() {
            let mesh = self.instance_mesh[i];
            self.tlas[i] = Some(wgpu::TlasInstance::new(
                &self.blases[mesh as usize],
                object_to_world(inst, i)?,
                mesh,
                (inst.mask & 0xff) as u8,
            ));
        }
        Ok(())
    }

    /// Builds (or updates) the TLAS, and the BLASes too when `meshes`, and waits.
    fn build(&mut self, meshes: bool) -> Result<(), GpuError> {
        let start = Instant::now();
        let device = self.ctx.device();
        let sizes: Vec<wgpu::BlasTriangleGeometrySizeDescriptor> =
            self.meshes.iter().map(blas_size).collect();
        let index = self
            .ctx
            .scoped("building the acceleration structures", || {
                let entries: Vec<wgpu::BlasBuildEntry<'_>> = if meshes {
                    self.meshes
                        .iter()
                        .zip(&self.blases)
                        .zip(&sizes)
                        .map(|((m, blas), size)| wgpu::BlasBuildEntry {
                            blas,
                            geometry: wgpu::BlasGeometries::TriangleGeometries(vec![
                                wgpu::BlasTriangleGeometry {
                                    size,
                                    vertex_buffer: &self.triangles,
                                    first_vertex: 3 * m.first,
                                    vertex_stride: 16,
                                    index_buffer: None,
                                    first_index: None,
                                    transform_buffer: None,
                                    transform_buffer_offset: None,
                                },
                            ]),
                        })
                        .collect()
                } else {
                    Vec::new()
                };
                let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                    label: Some("bvhtrace acceleration structures"),
                });
                enc.build_acceleration_structures(entries.iter(), std::iter::once(&self.tlas));
                self.ctx.queue().submit([enc.finish()])
            })?;
        device
            .poll(wgpu::PollType::Wait {
                submission_index: Some(index),
                timeout: None,
            })
            .map_err(|e| GpuError::device("building the acceleration structures", e))?;
        self.build_ms = start.elapsed().as_secs_f64() * 1e3;
        Ok(())
    }

    /// Wall time of the last acceleration-structure build, milliseconds: the BLASes and
    /// the TLAS at upload, the TLAS (and after a refit the BLASes, updated in place) at
    /// [`Tracer::update`].
    pub fn build_ms(&self) -> f64 {
        self.build_ms
    }

    /// The context.
    pub fn context(&self) -> &GpuContext {
        &self.ctx
    }

    /// True for a two-level BVH.
    pub fn is_instanced(&self) -> bool {
        self.instances.is_some()
    }

    /// True when the tree's alpha masks were uploaded (binding 5), which the kernels and
    /// libraries then cut candidates by.
    pub fn has_masks(&self) -> bool {
        self.masks.is_some()
    }

    /// The library shape this upload binds.
    fn library_shape(&self) -> LibraryShape {
        LibraryShape {
            masks: self.has_masks(),
            pages: self.pages,
            ..LibraryShape::ray_queries(self.is_instanced())
        }
    }

    /// Meshes (BLASes) and instances (TLAS entries).
    pub fn counts(&self) -> (usize, usize) {
        (self.meshes.len(), self.instance_mesh.len())
    }

    /// The traversal library over ray queries for your own shader
    /// ([`LibraryShape::ray_queries`], with [`LibraryShape::masks`] for a masked BVH), the
    /// BVH bindings in `@group(group)`: the same `bvh_trace_closest` and `bvh_trace_any` as
    /// the walks' libraries. Bind it with [`RayQueryBvh::bind_group_for`].
    pub fn wgsl_library(&self, group: u32) -> BvhLibrary {
        wgsl_library(self.library_shape(), group)
    }

    /// The bind group `library` reads, with its layout; [`TraceError::LibraryMismatch`]
    /// for a library composed for anything but this upload's ray queries (its levels and
    /// whether it has masks).
    pub fn bind_group_for(&self, library: &BvhLibrary) -> Result<BvhBindGroup<'_>, GpuError> {
        let holds = self.library_shape();
        let wanted = library.shape();
        let shape = |s: &LibraryShape| (s.instanced, s.masks, s.pages);
        if !wanted.ray_queries || shape(&wanted) != shape(&holds) {
            return Err(TraceError::LibraryMismatch {
                library: wanted.to_string(),
                upload: holds.to_string(),
            });
        }
        Ok(BvhBindGroup::new(self.group()?, &self.layout))
    }

    /// The BVH bind group (made at upload).
    fn group(&self) -> Result<&wgpu::BindGroup, GpuError> {
        self.group.as_ref().ok_or(GpuError::BadBuffer {
            buffer: "acceleration structure",
            problem: "not built".into(),
        })
    }

    /// The kernel for `any` hit or closest with the ray mask `mask`.
    fn pipeline(&self, any: bool, mask: u8) -> Result<wgpu::ComputePipeline, GpuError> {
        let poisoned = || GpuError::Poisoned("ray-query pipelines");
        if let Some(p) = self
            .pipelines
            .lock()
            .map_err(|_| poisoned())?
            .get(&(any, mask))
        {
            return Ok(p.clone());
        }
        let device = self.ctx.device();
        let source = bvhtrace_engine::ray_query::kernel_source(
            self.is_instanced(),
            self.has_masks(),
            self.pages,
        );
        let constants = [
            ("BVH_ANY_HIT", if any { 1.0 } else { 0.0 }),
            ("BVH_RAY_MASK", f64::from(mask)),
        ];
        let pipeline = self.ctx.scoped("creating the ray-query pipeline", || {
            let module = device.create_shader_module(wgpu::ShaderModuleDescriptor {
                label: Some("bvhtrace ray queries"),
                source: wgpu::ShaderSource::Wgsl(source.into()),
            });
            let layout = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor {
                label: Some("bvhtrace ray queries"),
                bind_group_layouts: &[
                    Some(&self.layout),
                    Some(self.ctx.batch_layout(false, RayInput::Buffer)),
                ],
                immediate_size: 0,
            });
            device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
                label: Some(bvhtrace_engine::ray_query::ENTRY_POINT),
                layout: Some(&layout),
                module: &module,
                entry_point: Some(bvhtrace_engine::ray_query::ENTRY_POINT),
                compilation_options: wgpu::PipelineCompilationOptions {
                    constants: &constants,
                    zero_initialize_workgroup_memory: false,
                },
                cache: None,
            })
        })?;
        self.pipelines
            .lock()
            .map_err(|_| poisoned())?
            .insert((any, mask), pipeline.clone());
        Ok(pipeline)
    }

    /// The masks' words for [`Tracer::update`] to write, after checking that `bvh`'s masks
    /// fit this upload: present as they were, the same size, on the same meshes (a BLAS's
    /// opacity is fixed when it is created).
    fn check_update_masks(&self, bvh: &FlatBvh) -> Result<Option<Vec<u32>>, TraceError> {
        let bad = |problem: String| TraceError::BadBuffer {
            buffer: "alpha masks",
            problem,
        };
        let words = masks_words(bvh);
        let had = self.masks.as_ref().map(|m| m.size());
        match (had, &words) {
            (None, None) => return Ok(None),
            (Some(bytes), Some(w)) if bytes == 4 * w.len() as u64 => {}
            (Some(bytes), Some(w)) => {
                return Err(bad(format!(
                    "the upload holds {bytes} bytes of masks and the update {}: upload again",
                    4 * w.len()
                )));
            }
            _ => {
                return Err(bad(format!(
                    "the upload was made {} alpha masks and the update has {}: upload again",
                    if had.is_some() { "with" } else { "without" },
                    if words.is_some() { "some" } else { "none" }
                )));
            }
        }
        let (meshes, _) = meshes_of(bvh)?;
        let opacity = |m: &[Mesh]| m.iter().map(|m| m.opaque).collect::<Vec<bool>>();
        if opacity(&meshes) != opacity(&self.meshes) {
            return Err(bad(
                "the masks now cover other meshes than at upload: upload again".into(),
            ));
        }
        Ok(words)
    }

    /// Traces `rays` in chunks of one dispatch each: upload, dispatch, read back, with as
    /// many chunks in flight as the tuning says ([`bvhtrace_engine::DriverTuning::in_flight`],
    /// each at most its `submission_rays` then), each on buffers of its own.
    async fn trace_chunks(
        &self,
        rays: &[Ray],
        opts: &TraceOptions,
    ) -> Result<TraceOutput, GpuError> {
        self.supports(opts)?;
        let start = Instant::now();
        let pipeline = self.pipeline(opts.query == Query::Any, opts.mask)?;
        let group = self.group()?;
        let tuning = self.ctx.tuning();
        let n = rays.len() as u64;
        let most = rays_per_dispatch(self.ctx.limits());
        let (chunk, slots) = submissions_in_flight(n, most, tuning);
        let chunk = chunk.min(n.max(1));
        let keep = tuning.in_flight > 1;
        let scratch = self.take_scratch(slots, chunk, keep)?;
        let traced = self
            .trace_in(&scratch[..slots], rays, chunk, &pipeline, group)
            .await;
        if keep && let Ok(mut kept) = self.scratch.lock() {
            *kept = scratch;
        }
        let (hits, phases) = traced?;
        Ok(TraceOutput {
            hits,
            counters: None,
            gpu_ms: None,
            wall_ms: start.elapsed().as_secs_f64() * 1e3,
            incomplete: 0,
            instances: self.table.clone(),
            phases: Some(phases),
        })
    }

    /// At least `slots` scratches of `capacity` rays or more: the kept ones when `keep`
    /// and they are large enough, else new ones.
    fn take_scratch(
        &self,
        slots: usize,
        capacity: u64,
        keep: bool,
    ) -> Result<Vec<RayQueryScratch>, GpuError> {
        let mut out = match keep {
            true => std::mem::take(
                &mut *self
                    .scratch
                    .lock()
                    .map_err(|_| TraceError::Poisoned("ray-query scratch buffers"))?,
            ),
            false => Vec::new(),
        };
        out.retain(|s| s.capacity >= capacity);
        let device = self.ctx.device();
        while out.len() < slots {
            let made = self.ctx.scoped("allocating the ray batch", || {
                RayQueryScratch::new(device, capacity)
            })?;
            out.push(made);
        }
        Ok(out)
    }

    /// Traces `rays` in chunks of `chunk` through `pipeline`, chunk `i` on scratch
    /// `i % scratch.len()`, as many in flight as there are scratches (the oldest read back
    /// before its scratch takes the next): the hits, and where the wall time went.
    async fn trace_in(
        &self,
        scratch: &[RayQueryScratch],
        rays: &[Ray],
        chunk: u64,
        pipeline: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
    ) -> Result<(Vec<Hit>, TracePhases), GpuError> {
        let mut phases = TracePhases::default();
        let mut hits = Vec::with_capacity(rays.len());
        let mut in_flight: std::collections::VecDeque<InFlight> = Default::default();
        for (i, part) in rays.chunks(chunk as usize).enumerate() {
            if in_flight.len() == scratch.len()
                && let Some(oldest) = in_flight.pop_front()
            {
                phases += self.read_chunk(scratch, oldest, &mut hits).await?;
            }
            let slot = i % scratch.len();
            let submitted = self.submit_chunk(&scratch[slot], part, pipeline, group)?;
            in_flight.push_back(InFlight { slot, ..submitted });
        }
        while let Some(oldest) = in_flight.pop_front() {
            phases += self.read_chunk(scratch, oldest, &mut hits).await?;
        }
        Ok((hits, phases))
    }

    /// Writes `part` to `s`, records its queries and the hits' copy for reading back, and
    /// submits them without waiting.
    fn submit_chunk(
        &self,
        s: &RayQueryScratch,
        part: &[Ray],
        pipeline: &wgpu::ComputePipeline,
        group: &wgpu::BindGroup,
    ) -> Result<InFlight, GpuError> {
        let device = self.ctx.device();
        let n = part.len() as u64;
        let started = Instant::now();
        let index = self.ctx.scoped("tracing a ray batch", || {
            self.ctx
                .queue()
                .write_buffer(&s.rays, 0, bytemuck::cast_slice(part));
            let batch = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("bvhtrace ray-query batch"),
                layout: self.ctx.batch_layout(false, RayInput::Buffer),
                entries: &[
                    wgpu::BindGroupEntry {
                        binding: 0,
                        resource: binding(&s.rays, 0, n, RAY_BYTES),
                    },
                    wgpu::BindGroupEntry {
                        binding: 1,
                        resource: binding(&s.hits, 0, n, HIT_BYTES),
                    },
                ],
            });
            let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor {
                label: Some("bvhtrace ray queries"),
            });
            {
                let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                    label: Some("bvhtrace ray queries"),
                    timestamp_writes: None,
                });
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, group, &[]);
                pass.set_bind_group(1, &batch, &[]);
                for d in plan_dispatches(n, self.ctx.limits()) {
                    pass.dispatch_workgroups(d.groups_x, d.groups_y, 1);
                }
            }
            enc.copy_buffer_to_buffer(&s.hits, 0, &s.read, 0, n * HIT_BYTES);
            self.ctx.queue().submit([enc.finish()])
        })?;
        Ok(InFlight {
            slot: 0,
            index,
            count: n,
            started,
            submitted: Instant::now(),
        })
    }

    /// Waits for `f`, appends its hits to `hits`, and says where its time went.
    async fn read_chunk(
        &self,
        scratch: &[RayQueryScratch],
        f: InFlight,
        hits: &mut Vec<Hit>,
    ) -> Result<TracePhases, GpuError> {
        let read = &scratch[f.slot].read;
        let bytes = f.count * HIT_BYTES;
        let mapped = map_all(&self.ctx, f.index, &[(read, bytes)]).await;
        self.ctx.deferred_errors().await?;
        mapped?;
        let done = Instant::now();
        let got = read_mapped(read, bytes, hits);
        read.unmap();
        got?;
        Ok(TracePhases::since(f.started, f.submitted, done))
    }
}

/// The size of a mesh's BLAS geometry: its triangles, unindexed, opaque unless an instance
/// of it has alpha masks (then its candidates reach the query loop, which tests them).
fn blas_size(m: &Mesh) -> wgpu::BlasTriangleGeometrySizeDescriptor {
    wgpu::BlasTriangleGeometrySizeDescriptor {
        vertex_format: wgpu::VertexFormat::Float32x3,
        vertex_count: 3 * m.count,
        index_format: None,
        index_count: None,
        flags: if m.opaque {
            wgpu::AccelerationStructureGeometryFlags::OPAQUE
        } else {
            wgpu::AccelerationStructureGeometryFlags::empty()
        },
    }
}

/// The alpha masks' words as the kernels read them (binding 5), the instance bases in
/// `FlatBvh::instances`' order, which is the TLAS's (`set_instances`), so the candidate's
/// instance index finds its base; `None` without masks.
fn masks_words(bvh: &FlatBvh) -> Option<Vec<u32>> {
    bvh.masks().map(|m| m.words(&m.instance_bases))
}

/// Each mesh (a BLAS: its root, triangle run and whether it is opaque) and each instance's
/// mesh; one mesh and one entry for a one-level tree.
fn meshes_of(bvh: &FlatBvh) -> Result<(Vec<Mesh>, Vec<u32>), TraceError> {
    if !bvh.is_instanced() {
        let mesh = Mesh {
            root: 0,
            first: 0,
            count: bvh.triangles().len() as u32,
            opaque: bvh.masks().is_none(),
        };
        return Ok((vec![mesh], vec![0]));
    }
    let mut meshes: Vec<Mesh> = Vec::new();
    let mut instance_mesh = Vec::with_capacity(bvh.instances().len());
    for (i, inst) in bvh.instances().iter().enumerate() {
        let index = match meshes.iter().position(|m| m.root == inst.root) {
            Some(k) => k,
            None => {
                let (first, count) = mesh_range(bvh.nodes(), inst.root)?;
                meshes.push(Mesh {
                    root: inst.root,
                    first,
                    count,
                    opaque: true,
                });
                meshes.len() - 1
            }
        };
        // An instance whose mesh has no masked triangle has no base: it stays opaque.
        if bvh
            .masks()
            .is_some_and(|m| m.base(Some(i as u32)) != NO_MASKS)
        {
            meshes[index].opaque = false;
        }
        instance_mesh.push(index as u32);
    }
    Ok((meshes, instance_mesh))
}

/// Bytes of one `FlatTriangle`.
const TRIANGLE_BYTES: u64 = std::mem::size_of::<bvhtrace_core::FlatTriangle>() as u64;

/// How the triangles `bytes` are bound on `ctx`'s device: in one binding, or in pages of
/// one binding each (ranges of the one buffer, whose size the device's largest buffer
/// bounds), within its storage buffers per stage.
fn triangle_pages(ctx: &GpuContext, bytes: &[u8]) -> Result<Pages, GpuError> {
    let limits = ctx.limits();
    if bytes.len() as u64 <= limits.max_storage_buffer_binding_size {
        return Ok(Pages::ONE);
    }
    check_buffer_size(
        &DeviceLimits {
            max_storage_buffer_binding_size: limits.max_buffer_size,
            ..*limits
        },
        "triangles",
        bytes.len() as u64,
    )?;
    let page_limits = DeviceLimits {
        // A page starts at a multiple of its size: a power of two, aligned as offsets must be.
        max_buffer_size: limits.max_storage_buffer_binding_size,
        ..*limits
    };
    let array = DeviceArray {
        role: ArrayRole::Triangles,
        bytes: std::borrow::Cow::Borrowed(bytes),
        texel_bytes: None,
        page: 0,
    };
    let pages = Pages::plan(BvhStorage::Buffers, &[array], &page_limits)?;
    // Beside the pages: the batch's rays and hits, the meshes' firsts, the instances and
    // the masks (the TLAS is no storage buffer).
    let needs = u64::from(pages.triangles) + 5;
    let needed_for = "triangles larger than one binding, split into pages of one binding each,";
    check_storage_buffers(needs, limits, needed_for)?;
    Ok(pages)
}

/// The BVH group's layout: the TLAS (0), the triangles (1, and a binding per further
/// page), for two levels the meshes' first slots (2) and the instances (4), for a masked
/// BVH the masks (5).
fn group_layout(
    device: &wgpu::Device,
    instanced: bool,
    masks: bool,
    pages: Pages,
) -> wgpu::BindGroupLayout {
    let mut entries = vec![wgpu::BindGroupLayoutEntry {
        binding: 0,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::AccelerationStructure {
            vertex_return: false,
        },
        count: None,
    }];
    for p in 0..u32::from(pages.triangles) {
        entries.push(storage_entry(1 + PAGE_BINDING_STRIDE * p, true));
    }
    if instanced {
        entries.extend([storage_entry(2, true), storage_entry(4, true)]);
    }
    if masks {
        entries.push(storage_entry(5, true));
    }
    device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor {
        label: Some("bvhtrace ray-query bvh"),
        entries: &entries,
    })
}

impl Tracer for RayQueryBvh {
    fn backend(&self) -> &'static str {
        RAY_QUERY_BACKEND
    }

    fn device_name(&self) -> String {
        let i = self.ctx.adapter_info();
        format!("{} ({:?}, Vulkan ray queries)", i.name, i.device_type)
    }

    /// The walk is the driver's; the traversal field of the options is not read.
    fn default_traversal(&self) -> bvhtrace_core::Traversal {
        bvhtrace_core::Traversal::GPU_DEFAULT
    }

    fn supports(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        if opts.counters {
            return Err(TraceError::Unsupported {
                backend: RAY_QUERY_BACKEND,
                what: "counters (the driver's walk is not counted): trace with our walks".into(),
            });
        }
        if opts.precision != Precision::WatertightF32 {
            return Err(TraceError::Unsupported {
                backend: RAY_QUERY_BACKEND,
                what: format!(
                    "the {} triangle test (the driver's test answers): trace with our walks",
                    opts.precision
                ),
            });
        }
        Ok(())
    }

    fn trace(&self, rays: &[Ray], opts: &TraceOptions) -> Result<TraceOutput, TraceError> {
        pollster::block_on(self.trace_chunks(rays, opts))
    }

    fn trace_async<'a>(
        &'a self,
        rays: &'a [Ray],
        opts: &'a TraceOptions,
    ) -> bvhtrace_engine::tracer::TraceFuture<'a> {
        Box::pin(self.trace_chunks(rays, opts))
    }

    fn prepare(&self, opts: &TraceOptions) -> Result<(), TraceError> {
        self.supports(opts)?;
        self.pipeline(opts.query == Query::Any, opts.mask)
            .map(|_| ())
    }

    fn upload_stats(&self) -> Option<UploadStats> {
        Some(self.stats)
    }

    fn device_build_ms(&self) -> Option<f64> {
        Some(self.build_ms)
    }

    /// Instances moved: the TLAS is rebuilt with their new transforms and masks. Meshes
    /// refitted (the triangles changed): the triangles are written again and every BLAS
    /// updated in place, then the TLAS rebuilt. The alpha masks are written again; a tree
    /// that gains or loses masks, or whose masks change size or which meshes they touch,
    /// is a [`TraceError::BadBuffer`]: upload it again.
    fn update(&mut self, bvh: &FlatBvh) -> Result<(), TraceError> {
        check_update_shape(self.shape, bvh)?;
        let words = self.check_update_masks(bvh)?;
        let fingerprint = mesh_fingerprint(bvh);
        let meshes = !bvh.is_instanced() || fingerprint != self.fingerprint;
        let queue = self.ctx.queue().clone();
        self.ctx
            .scoped("updating the acceleration structures", || {
                if meshes {
                    queue.write_buffer(&self.triangles, 0, bytemuck::cast_slice(bvh.triangles()));
                }
                if let Some(i) = &self.instances {
                    queue.write_buffer(i, 0, bytemuck::cast_slice(bvh.instances()));
                }
                if let (Some(m), Some(w)) = (&self.masks, &words) {
                    queue.write_buffer(m, 0, bytemuck::cast_slice(w));
                }
            })?;
        self.set_instances(bvh)?;
        self.build(meshes)?;
        self.fingerprint = fingerprint;
        self.table = InstanceTable::of(bvh);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_inverted_transform_takes_object_points_back_to_world() {
        // world_to_object of "scale by 2, then translate by (1, 2, 3)".
        let inst = FlatInstance {
            world_to_object: [
                [0.5, 0.0, 0.0, -0.5],
                [0.0, 0.5, 0.0, -1.0],
                [0.0, 0.0, 0.5, -1.5],
            ],
            root: 0,
            prim_base: 0,
            mask: 0xff,
            user_id: 0,
        };
        let m = object_to_world(&inst, 0).expect("invertible");
        assert_eq!(
            m,
            [2.0, 0.0, 0.0, 1.0, 0.0, 2.0, 0.0, 2.0, 0.0, 0.0, 2.0, 3.0]
        );
        let singular = FlatInstance {
            world_to_object: [[0.0; 4]; 3],
            ..inst
        };
        let err = object_to_world(&singular, 7).expect_err("singular");
        assert!(err.to_string().contains("instance 7"), "{err}");
    }

    #[test]
    fn a_mesh_is_the_run_of_triangles_under_its_root() {
        let tris: Vec<[glam::Vec3; 3]> = (0..40)
            .map(|i| {
                let x = i as f32;
                [
                    glam::Vec3::new(x, 0.0, 0.0),
                    glam::Vec3::new(x + 1.0, 0.0, 0.0),
                    glam::Vec3::new(x, 1.0, 0.0),
                ]
            })
            .collect();
        let bvh = FlatBvh::build(&tris, &bvhtrace_core::BuildOptions::default()).expect("builds");
        assert_eq!(mesh_range(bvh.nodes(), 0).expect("one run"), (0, 40));
        let second = bvh.nodes()[0].right_or_first;
        let (first, count) = mesh_range(bvh.nodes(), second).expect("one run");
        assert_eq!(first + count, 40);
        assert!(count > 0 && count < 40);
    }
}
