//! The wgpu implementation of the engine's [`Backend`]: the BVH's arrays in buffers or
//! texel textures with their bind groups, the ray scratch, one batch per submission.

use std::sync::Mutex;

use bvhtrace_core::Traversal;
use bvhtrace_engine::engine::{ArrayWrite, ArraysLayout, Batch, BatchOut, BatchTimes, ScratchPlan};
use bvhtrace_engine::engine::{BackendFeatures, DeviceApi};
use bvhtrace_engine::pages::PAGE_BINDING_STRIDE;
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::storage::texel_extent;
use bvhtrace_engine::upload::{ArrayRole, DeviceArray};
use bvhtrace_engine::{DriverTuning, KernelKey, TraceError};
use wgpu::util::DeviceExt;

use crate::context::{BvhGroupShape, GpuContext};
use crate::trace::{BatchGroups, Scratch, Submitted};

/// The wgpu device behind a [`crate::GpuBvh`]: the engine's backend on wgpu.
pub struct Wgpu {
    pub(crate) ctx: GpuContext,
}

/// One uploaded array.
pub(crate) enum Resource {
    Buffer(wgpu::Buffer),
    Texture(wgpu::Texture, wgpu::TextureView),
}

impl Resource {
    fn entry(&self, binding: u32) -> wgpu::BindGroupEntry<'_> {
        wgpu::BindGroupEntry {
            binding,
            resource: match self {
                Resource::Buffer(b) => b.as_entire_binding(),
                Resource::Texture(_, v) => wgpu::BindingResource::TextureView(v),
            },
        }
    }
}

/// A bind group and its layout.
type Group = (wgpu::BindGroup, wgpu::BindGroupLayout);

/// The uploaded arrays and their bind groups.
pub struct WgpuArrays {
    /// Each array (each page of a split one) by role and page.
    resources: Vec<((ArrayRole, u8), Resource)>,
    /// The BVH group for the full-stack kernels (nodes, triangles).
    plain: Option<Group>,
    /// The BVH group for the escape-link kernels.
    escapes: Option<Group>,
    /// The wide layout's group.
    wide: Option<Group>,
    /// The batch bind groups made so far ([`crate::trace`]).
    pub(crate) batch_groups: Mutex<BatchGroups>,
}

impl WgpuArrays {
    /// The array in `role` (its first page, when split), when uploaded.
    pub(crate) fn get(&self, role: ArrayRole) -> Option<&Resource> {
        self.resources
            .iter()
            .find(|(r, _)| *r == (role, 0))
            .map(|(_, res)| res)
    }

    /// True when some array was split into pages: the accessors of single buffers
    /// ([`WgpuArrays::buffer`]) then answer `None`.
    pub(crate) fn is_split(&self) -> bool {
        self.resources.iter().any(|((_, page), _)| *page > 0)
    }

    /// The buffer in `role`, when uploaded as one (and not split into pages).
    pub(crate) fn buffer(&self, role: ArrayRole) -> Option<&wgpu::Buffer> {
        match self.get(role) {
            Some(Resource::Buffer(b)) if !self.is_split() => Some(b),
            _ => None,
        }
    }

    /// The buffers of `role`'s pages in page order (one for an array not split; none when
    /// not uploaded, or in a texture).
    pub(crate) fn buffer_pages(&self, role: ArrayRole) -> Vec<&wgpu::Buffer> {
        let mut pages: Vec<(u8, &wgpu::Buffer)> = (self.resources.iter())
            .filter_map(|((r, p), res)| match res {
                Resource::Buffer(b) if *r == role => Some((*p, b)),
                _ => None,
            })
            .collect();
        pages.sort_by_key(|(p, _)| *p);
        pages.into_iter().map(|(_, b)| b).collect()
    }

    /// The texture in `role`, when uploaded as one.
    pub(crate) fn texture(&self, role: ArrayRole) -> Option<&wgpu::Texture> {
        match self.get(role) {
            Some(Resource::Texture(t, _)) => Some(t),
            _ => None,
        }
    }

    /// The BVH bind group `traversal` reads and its layout, when uploaded.
    pub(crate) fn group(
        &self,
        traversal: Traversal,
    ) -> Option<(&wgpu::BindGroup, &wgpu::BindGroupLayout)> {
        let g = if traversal.is_wide() {
            self.wide.as_ref()
        } else if traversal.needs_escapes() {
            self.escapes.as_ref()
        } else {
            self.plain.as_ref()
        };
        g.map(|(group, layout)| (group, layout))
    }

    /// (Re)makes the bind groups of the arrays there are.
    fn bind(&mut self, ctx: &GpuContext, layout: ArraysLayout) {
        let device = ctx.device();
        let group = |label: &str, escapes: bool, roles: &[ArrayRole]| {
            let wide = roles.contains(&ArrayRole::WideNodes);
            let entries: Vec<_> = (self.resources.iter())
                .filter(|((r, _), _)| roles.contains(r))
                .map(|&((r, page), ref res)| {
                    res.entry(r.binding() + PAGE_BINDING_STRIDE * u32::from(page))
                })
                .collect();
            let bgl = ctx.bvh_layout_of(BvhGroupShape {
                storage: layout.storage,
                escapes,
                instances: layout.instanced,
                masks: layout.masks,
                pages: if wide {
                    layout.wide_pages
                } else {
                    layout.pages
                },
            });
            let bg = device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(label),
                layout: &bgl,
                entries: &entries,
            });
            (bg, bgl)
        };
        use ArrayRole as R;
        let binary = self.get(R::Nodes).is_some();
        // The wide group uses the binary layout's: binding types say nothing of what the
        // elements or texels hold.
        let plain = binary.then(|| {
            group(
                "bvhtrace bvh",
                false,
                &[R::Nodes, R::Triangles, R::Instances, R::Masks],
            )
        });
        let escapes = self.get(R::Escapes).is_some().then(|| {
            group(
                "bvhtrace bvh+escapes",
                true,
                &[R::Nodes, R::Triangles, R::Escapes, R::Instances, R::Masks],
            )
        });
        let wide = self.get(R::WideNodes).is_some().then(|| {
            group(
                "bvhtrace bvh (wide)",
                false,
                &[
                    R::WideNodes,
                    R::WideTriangles,
                    R::WideInstances,
                    R::WideMasks,
                ],
            )
        });
        (self.plain, self.escapes, self.wide) = (plain, escapes, wide);
    }
}

/// A `width` x `rows` storage texture, filled by copies and copied from: the BVH's texel
/// textures and the trace's ray texture (read-only in the kernels), and its hit texture
/// (write-only).
pub(crate) fn storage_texture(
    ctx: &GpuContext,
    label: &str,
    format: wgpu::TextureFormat,
    width: u32,
    rows: u32,
) -> wgpu::Texture {
    ctx.device().create_texture(&wgpu::TextureDescriptor {
        label: Some(label),
        size: wgpu::Extent3d {
            width,
            height: rows,
            depth_or_array_layers: 1,
        },
        mip_level_count: 1,
        sample_count: 1,
        dimension: wgpu::TextureDimension::D2,
        format,
        usage: wgpu::TextureUsages::STORAGE_BINDING
            | wgpu::TextureUsages::COPY_DST
            | wgpu::TextureUsages::COPY_SRC,
        view_formats: &[],
    })
}

/// Writes `bytes`, texels of `texel` bytes, over `texture` from its first texel on, row by
/// row: the whole rows as they are, the rest in one zero-padded row.
pub(crate) fn write_texels(queue: &wgpu::Queue, texture: &wgpu::Texture, bytes: &[u8], texel: u64) {
    let width = texture.width();
    let row = (u64::from(width) * texel) as usize;
    let full = bytes.len() / row;
    let mut last = bytes[full * row..].to_vec();
    last.resize(if last.is_empty() { 0 } else { row }, 0);
    for (y, part) in [(0, &bytes[..full * row]), (full as u32, &last[..])] {
        if part.is_empty() {
            continue;
        }
        queue.write_texture(
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: 0,
                origin: wgpu::Origin3d { x: 0, y, z: 0 },
                aspect: wgpu::TextureAspect::All,
            },
            part,
            wgpu::TexelCopyBufferLayout {
                offset: 0,
                bytes_per_row: Some(row as u32),
                rows_per_image: None,
            },
            wgpu::Extent3d {
                width,
                height: (part.len() / row) as u32,
                depth_or_array_layers: 1,
            },
        );
    }
}

impl Wgpu {
    /// Creates and fills the device copy of `a`.
    fn make(&self, a: &DeviceArray<'_>) -> Resource {
        let label = format!("bvhtrace {}", a.name());
        match a.texel_bytes {
            None => Resource::Buffer(self.ctx.device().create_buffer_init(
                &wgpu::util::BufferInitDescriptor {
                    label: Some(&label),
                    contents: &a.bytes,
                    // COPY_SRC: a refit on the device reads its tree back for the host copy.
                    usage: wgpu::BufferUsages::STORAGE
                        | wgpu::BufferUsages::COPY_DST
                        | wgpu::BufferUsages::COPY_SRC,
                },
            )),
            Some(texel) => {
                let format = match texel {
                    4 => wgpu::TextureFormat::R32Uint,
                    _ => wgpu::TextureFormat::Rgba32Uint,
                };
                let (w, h) = texel_extent(a.texels());
                let t = storage_texture(&self.ctx, &label, format, w, h);
                write_texels(self.ctx.queue(), &t, &a.bytes, texel);
                let v = t.create_view(&Default::default());
                Resource::Texture(t, v)
            }
        }
    }

    /// Waits until every write so far has reached the device.
    fn settle(&self, during: &'static str) -> Result<(), TraceError> {
        let index = self.ctx.queue().submit([]);
        self.ctx
            .device()
            .poll(wgpu::PollType::Wait {
                submission_index: Some(index),
                timeout: None,
            })
            .map(|_| ())
            .map_err(|e| TraceError::device(during, e))
    }
}

impl DeviceApi for Wgpu {
    type Arrays = WgpuArrays;
    type Scratch = Scratch;
    type Submitted = Submitted;

    fn name(&self) -> &'static str {
        "wgpu"
    }

    fn device_name(&self) -> String {
        let i = self.ctx.adapter_info();
        format!("{} ({:?}, {:?})", i.name, i.device_type, i.backend)
    }

    fn limits(&self) -> &DeviceLimits {
        self.ctx.limits()
    }

    fn tuning(&self) -> &DriverTuning {
        self.ctx.tuning()
    }

    fn has_timestamps(&self) -> bool {
        self.ctx.has_timestamps()
    }

    fn features(&self) -> BackendFeatures {
        self.ctx.features()
    }

    fn prepare_kernel(&self, key: KernelKey) -> Result<(), TraceError> {
        self.ctx.pipeline(key).map(|_| ())
    }

    fn create_arrays(
        &self,
        layout: ArraysLayout,
        arrays: &[DeviceArray<'_>],
    ) -> Result<WgpuArrays, TraceError> {
        let mut made = self.ctx.scoped("uploading the BVH", || WgpuArrays {
            resources: (arrays.iter())
                .map(|a| ((a.role, a.page), self.make(a)))
                .collect(),
            plain: None,
            escapes: None,
            wide: None,
            batch_groups: Mutex::new(Default::default()),
        })?;
        self.ctx
            .scoped("binding the BVH", || made.bind(&self.ctx, layout))?;
        self.settle("uploading the BVH")?;
        Ok(made)
    }

    fn write_arrays(
        &self,
        arrays: &mut WgpuArrays,
        layout: ArraysLayout,
        writes: &[ArrayWrite<'_>],
    ) -> Result<(), TraceError> {
        let rebind = self.ctx.scoped("updating the BVH", || {
            let mut rebind = false;
            for w in writes {
                let a = &w.array;
                let at = (arrays.resources.iter()).position(|(r, _)| *r == (a.role, a.page));
                match (at, w.replace) {
                    (Some(i), false) => match (&arrays.resources[i].1, a.texel_bytes) {
                        (Resource::Buffer(b), _) => self.ctx.queue().write_buffer(b, 0, &a.bytes),
                        (Resource::Texture(t, _), Some(texel)) => {
                            write_texels(self.ctx.queue(), t, &a.bytes, texel)
                        }
                        (Resource::Texture(..), None) => {}
                    },
                    (Some(i), true) => {
                        arrays.resources[i].1 = self.make(a);
                        rebind = true;
                    }
                    (None, _) => {
                        arrays.resources.push(((a.role, a.page), self.make(a)));
                        rebind = true;
                    }
                }
            }
            rebind
        })?;
        if rebind {
            self.ctx
                .scoped("binding the BVH", || arrays.bind(&self.ctx, layout))?;
        }
        Ok(())
    }

    fn create_scratch(&self, plan: &ScratchPlan) -> Result<Scratch, TraceError> {
        self.ctx
            .scoped("allocating ray buffers", || Scratch::new(&self.ctx, plan))
    }

    fn submit_batch(
        &self,
        arrays: &WgpuArrays,
        scratch: &Scratch,
        batch: Batch<'_>,
    ) -> Result<Submitted, TraceError> {
        crate::trace::submit_batch(&self.ctx, arrays, scratch, batch)
    }

    fn finish_batch<'a>(
        &'a self,
        scratch: &'a Scratch,
        submitted: Submitted,
        out: BatchOut<'a>,
    ) -> impl Future<Output = Result<BatchTimes, TraceError>> + 'a {
        crate::trace::finish_batch(&self.ctx, scratch, submitted, out)
    }
}
