//! A [`FlatBvh`] on a wgpu device: [`GpuBvh`], the engine
//! ([`bvhtrace_engine::Engine`]) over the wgpu backend, and its wgpu-only surfaces (bind
//! groups, buffers and textures for your own shaders, recording into your encoder).

use bvhtrace_core::{FlatBvh, Traversal};
#[cfg(doc)]
use bvhtrace_engine::Tracer;
use bvhtrace_engine::engine::{HasEngine, UploadedTree};
use bvhtrace_engine::upload::ArrayRole;
use bvhtrace_engine::{Engine, UploadOptions, UploadStats};

use crate::GpuError;
use crate::backend::Wgpu;
use crate::context::GpuContext;

/// The BVH bind group of one upload, for group 0 of the kernels or any group of your own
/// shader ([`bvhtrace_engine::wgsl_library`]), with the layout
/// [`BvhBindGroup::layout`] names.
#[derive(Clone, Copy, Debug)]
pub struct BvhBindGroup<'a> {
    group: &'a wgpu::BindGroup,
    layout: &'a wgpu::BindGroupLayout,
}

impl<'a> BvhBindGroup<'a> {
    // Only the ray-query tracer, which a browser build leaves out, makes one this way.
    #[cfg_attr(target_arch = "wasm32", allow(dead_code))]
    pub(crate) fn new(group: &'a wgpu::BindGroup, layout: &'a wgpu::BindGroupLayout) -> Self {
        BvhBindGroup { group, layout }
    }

    /// The bind group.
    pub fn group(&self) -> &'a wgpu::BindGroup {
        self.group
    }

    /// Its layout, for your pipeline layout.
    pub fn layout(&self) -> &'a wgpu::BindGroupLayout {
        self.layout
    }
}

/// A BVH on the device, ready to trace (see [`trace`](crate::Tracer::trace) and
/// [`GpuBvh::record`]).
/// `Send + Sync`: trace it from several threads at once.
///
/// [`Tracer`] is implemented by the engine ([`HasEngine::engine`] gives it, for what
/// only a backend implementer asks of it).
pub struct GpuBvh {
    pub(crate) engine: Engine<Wgpu>,
}

impl HasEngine for GpuBvh {
    type Device = Wgpu;
    fn engine(&self) -> &Engine<Wgpu> {
        &self.engine
    }
    fn engine_mut(&mut self) -> &mut Engine<Wgpu> {
        &mut self.engine
    }
}

impl std::fmt::Debug for GpuBvh {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GpuBvh")
            .field("tree", self.engine.tree())
            .field("stats", self.engine.stats())
            .finish()
    }
}

impl GpuBvh {
    /// Uploads `bvh` as `opts` says, as buffers or textures (`opts.storage`), by the rules
    /// every backend follows ([`Engine::upload`]): the escape links only when a listed walk
    /// follows them, the wide layout when [`Traversal::Wide`] is listed, every array
    /// checked against the device's limits first. The [`UploadStats`] are those of both
    /// layouts together.
    pub fn upload(
        ctx: &GpuContext,
        bvh: &FlatBvh,
        opts: &UploadOptions,
    ) -> Result<GpuBvh, GpuError> {
        let backend = Wgpu { ctx: ctx.clone() };
        Ok(GpuBvh {
            engine: Engine::upload(backend, bvh, opts)?,
        })
    }

    /// What the upload holds: storage, one mesh or two levels, masks, layouts, depth.
    pub fn tree(&self) -> &UploadedTree {
        self.engine.tree()
    }

    /// What the upload holds and cost (both layouts together).
    pub fn stats(&self) -> &UploadStats {
        self.engine.stats()
    }

    /// Device bytes of the buffers [`trace`](crate::Tracer::trace) keeps between calls:
    /// rays, hits and their readback copy, and the counters (with theirs) only once a trace
    /// asked for them; a set for each submission in flight (`DriverTuning::in_flight`).
    pub fn scratch_bytes(&self) -> u64 {
        self.engine
            .with_scratch(|s| s.iter().map(|s| s.bytes()).sum())
    }

    /// The context this BVH lives in.
    pub fn context(&self) -> &GpuContext {
        &self.engine.device().ctx
    }

    /// The BVH bind group that `traversal`'s kernels read (nodes and triangles, the escape
    /// links for the walks that follow them, the instances for two levels; for
    /// [`Traversal::Wide`] the wide layout's), with its layout. For your own shader use
    /// [`GpuBvh::bind_group_for`], which checks the library against the upload.
    pub fn bind_group(&self, traversal: Traversal) -> Result<BvhBindGroup<'_>, GpuError> {
        self.engine.supports_traversal(traversal)?;
        let (group, layout) = (self.engine.arrays().group(traversal))
            .ok_or(GpuError::TraversalNotUploaded { traversal })?;
        Ok(BvhBindGroup { group, layout })
    }

    /// The node buffer (`array<Node>`), for [`crate::BvhStorage::Buffers`] uploads of the binary
    /// layout in one binding (`None` for a tree split into pages: bind it with
    /// [`GpuBvh::bind_group_for`]).
    pub fn nodes_buffer(&self) -> Option<&wgpu::Buffer> {
        self.engine.arrays().buffer(ArrayRole::Nodes)
    }

    /// The triangle buffer (`array<Triangle>`), for [`crate::BvhStorage::Buffers`] uploads of the
    /// binary layout in one binding (`None` for a tree split into pages).
    pub fn triangles_buffer(&self) -> Option<&wgpu::Buffer> {
        self.engine.arrays().buffer(ArrayRole::Triangles)
    }

    /// The escape-link buffer (`array<u32>`, eight links per node), for
    /// [`crate::BvhStorage::Buffers`] uploads with the escape links in one binding (`None`
    /// for a tree split into pages).
    pub fn escapes_buffer(&self) -> Option<&wgpu::Buffer> {
        self.engine.arrays().buffer(ArrayRole::Escapes)
    }

    /// The wide layout's buffers (`array<BvhWideNode>`, its triangles), when it was
    /// uploaded in [`crate::BvhStorage::Buffers`] in one binding each (`None` for a tree
    /// split into pages).
    pub fn wide_buffers(&self) -> Option<(&wgpu::Buffer, &wgpu::Buffer)> {
        let a = self.engine.arrays();
        a.buffer(ArrayRole::WideNodes)
            .zip(a.buffer(ArrayRole::WideTriangles))
    }

    /// The wide layout's textures (five `Rgba32Uint` texels per node, three per triangle,
    /// [`TEXEL_ROW`](bvhtrace_engine::storage::TEXEL_ROW) texels a row: `bvh_textures_wide.wgsl`),
    /// when it was uploaded in [`crate::BvhStorage::Textures`].
    pub fn wide_textures(&self) -> Option<(&wgpu::Texture, &wgpu::Texture)> {
        let a = self.engine.arrays();
        a.texture(ArrayRole::WideNodes)
            .zip(a.texture(ArrayRole::WideTriangles))
    }
}
