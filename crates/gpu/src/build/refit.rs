//! The BVH refitted on the device: after a one-mesh tree's vertices moved there (your
//! compute pass, a skinning pass, or a vertex upload), its corners and boxes are rewritten
//! in place, bottom up, and the tree kept (`shaders/refit.wgsl`, the twin of
//! [`FlatBvh::refit`], box for box).
//!
//! [`GpuRefit::new`] prepares one refit of one upload from one set of vertex buffers (the
//! nodes' order by level, one bind group per dispatch); [`GpuRefit::refit`] runs it and
//! waits, [`GpuRefit::record`] records it into your encoder.

use std::time::Instant;

use bvhtrace_core::{FlatBvh, FlatNode, FlatTriangle};
use bvhtrace_engine::BvhStorage;
use bvhtrace_engine::engine::HasEngine;
use bvhtrace_engine::pages::{PAGE_BINDING_STRIDE, Pages};
use bvhtrace_engine::programs::{REFIT_STEPS, RefitParams, refit_source_for};
use bvhtrace_engine::tracer::check_update_shape;
use bvhtrace_engine::upload::ArrayRole;

use super::{PARAMS_STRIDE, StepQueries, empty, grid, init, read_after, submit_and_map};
use crate::trace::read_mapped;
use crate::{GpuBvh, GpuContext, GpuError};

/// Where a refit reads the moved vertices: your buffers, bound as storage (created with
/// `BufferUsages::STORAGE`).
#[derive(Clone, Copy, Debug)]
pub struct RefitVertices<'a> {
    /// Vertex positions as `f32`s: vertex `v` is `positions[v * stride ..][..3]`.
    pub positions: &'a wgpu::Buffer,
    /// Floats from one vertex to the next: 3 for packed `xyz`, 4 for `vec4`s.
    pub stride: u32,
    /// Vertices in `positions`.
    pub vertices: u32,
    /// `u32` indices, three per triangle in the builder's input order; `None`: triangle
    /// `t`'s corners are vertices `3t`, `3t + 1`, `3t + 2`.
    pub indices: Option<&'a wgpu::Buffer>,
}

/// What one [`GpuRefit::refit`] cost.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RefitTimes {
    /// From submission to the status read back, host wall time, milliseconds.
    pub wall_ms: f64,
    /// The dispatches by timestamp queries, when the device has them.
    pub gpu_ms: Option<f64>,
    /// Dispatches: the check, the corners, one per level of boxes, and the node texels
    /// for an upload in textures.
    pub dispatches: usize,
    /// Reading the refitted tree back for the host copy (a CPU driver finishes the rays
    /// its trip budget leaves incomplete on it), milliseconds; 0 when none is kept.
    pub host_copy_ms: f64,
}

/// A refit of one uploaded one-mesh BVH from one set of vertex buffers, prepared once and
/// run each time the vertices move. The BVH may be in buffers (refitted in place) or in
/// textures (refitted in buffers of the refit's own, then copied over them), without the
/// wide layout (whose compressed boxes are collapsed on the CPU: refit there,
/// [`FlatBvh::refit`], and update).
#[derive(Debug)]
pub struct GpuRefit {
    ctx: GpuContext,
    pipelines: Vec<wgpu::ComputePipeline>,
    /// One per dispatch: its step, bind group and grid.
    dispatches: Vec<(usize, wgpu::BindGroup, (u32, u32))>,
    status: wgpu::Buffer,
    status_read: wgpu::Buffer,
    /// The nodes and triangles the refit writes (the upload's, page by page when split
    /// into pages, or its own when the upload is in textures), and the tree's depth, for
    /// the host copy.
    nodes: Vec<wgpu::Buffer>,
    triangles: Vec<wgpu::Buffer>,
    /// How the tree is split over bindings.
    pages: Pages,
    /// For an upload in textures: the nodes as texels, and the node and triangle
    /// textures they and `triangles` are copied over after each refit.
    textures: Option<(wgpu::Buffer, (wgpu::Texture, wgpu::Texture))>,
    counts: (u64, u64),
    depth: u32,
}

/// The node indices by level: every leaf, then the interior nodes deepest first; and the
/// length of each run.
fn levels(nodes: &[FlatNode]) -> (Vec<u32>, Vec<u32>) {
    let mut depth = vec![0u32; nodes.len()];
    let mut leaves = Vec::new();
    let mut interior: Vec<Vec<u32>> = Vec::new();
    for (i, n) in nodes.iter().enumerate() {
        let d = depth[i];
        if n.is_leaf() {
            leaves.push(i as u32);
            continue;
        }
        depth[i + 1] = d + 1;
        depth[n.right_or_first as usize] = d + 1;
        if interior.len() <= d as usize {
            interior.resize_with(d as usize + 1, Vec::new);
        }
        interior[d as usize].push(i as u32);
    }
    let mut runs = vec![leaves.len() as u32];
    let mut order = leaves;
    for level in interior.into_iter().rev() {
        runs.push(level.len() as u32);
        order.extend(level);
    }
    (order, runs)
}

/// The node and triangle buffers a refit of `bvh` (uploaded from `tree`) writes: the
/// upload's own in buffers (each page of a tree split into pages); in textures, buffers of
/// the refit's own holding `tree`, with the textures they are copied over.
#[allow(clippy::type_complexity)]
fn target_arrays(
    ctx: &GpuContext,
    bvh: &GpuBvh,
    tree: &FlatBvh,
) -> Result<
    (
        Vec<wgpu::Buffer>,
        Vec<wgpu::Buffer>,
        Option<(wgpu::Texture, wgpu::Texture)>,
    ),
    GpuError,
> {
    let arrays = bvh.engine().arrays();
    let missing = || unsupported("an upload without its binary layout");
    match bvh.engine().storage() {
        BvhStorage::Buffers => {
            let pages = |role| -> Result<Vec<wgpu::Buffer>, GpuError> {
                let pages = arrays.buffer_pages(role);
                match pages.is_empty() {
                    true => Err(missing()),
                    false => Ok(pages.into_iter().cloned().collect()),
                }
            };
            Ok((pages(ArrayRole::Nodes)?, pages(ArrayRole::Triangles)?, None))
        }
        BvhStorage::Textures => {
            let n = arrays.texture(ArrayRole::Nodes).ok_or_else(missing)?;
            let t = arrays.texture(ArrayRole::Triangles).ok_or_else(missing)?;
            let usage = wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_SRC;
            let device = ctx.device();
            Ok((
                vec![init(
                    device,
                    "refit nodes",
                    bytemuck::cast_slice(tree.nodes()),
                    usage,
                )],
                vec![init(
                    device,
                    "refit triangles",
                    bytemuck::cast_slice(tree.triangles()),
                    usage,
                )],
                Some((n.clone(), t.clone())),
            ))
        }
    }
}

/// Each page of an array of `bytes` bytes with the bytes it holds: full pages of
/// `page_bytes`, then what is left in the last (one page holds them all).
fn page_sources(pages: &[wgpu::Buffer], bytes: u64, page_bytes: u64) -> Vec<(&wgpu::Buffer, u64)> {
    let page = if pages.len() == 1 { bytes } else { page_bytes };
    (pages.iter().enumerate())
        .map(|(p, b)| (b, page.min(bytes.saturating_sub(page * p as u64))))
        .collect()
}

/// Copies `texels` 16-byte texels of `buffer` over `texture` from its first texel: the
/// whole rows, then what is left in one row.
fn copy_texels(
    enc: &mut wgpu::CommandEncoder,
    buffer: &wgpu::Buffer,
    texture: &wgpu::Texture,
    texels: u64,
) {
    let width = u64::from(texture.width());
    let (full, rest) = (texels / width, texels % width);
    for (y, rows, w) in [(0, full, width), (full, u64::from(rest > 0), rest)] {
        if rows == 0 {
            continue;
        }
        enc.copy_buffer_to_texture(
            wgpu::TexelCopyBufferInfo {
                buffer,
                layout: wgpu::TexelCopyBufferLayout {
                    offset: y * width * 16,
                    // Needed (and then 256-aligned: rows are TEXEL_ROW wide) past one row.
                    bytes_per_row: (rows > 1).then_some((width * 16) as u32),
                    rows_per_image: None,
                },
            },
            wgpu::TexelCopyTextureInfo {
                texture,
                mip_level: 0,
                origin: wgpu::Origin3d {
                    x: 0,
                    y: y as u32,
                    z: 0,
                },
                aspect: wgpu::TextureAspect::All,
            },
            wgpu::Extent3d {
                width: w as u32,
                height: rows as u32,
                depth_or_array_layers: 1,
            },
        );
    }
}

fn unsupported(what: &str) -> GpuError {
    GpuError::Unsupported {
        backend: "wgpu",
        what: format!("a refit on the device of {what}"),
    }
}

/// Checks that `bvh` (uploaded from `tree`) and `v` can be refitted together.
fn check(bvh: &GpuBvh, tree: &FlatBvh, v: &RefitVertices<'_>) -> Result<(), GpuError> {
    let engine = bvh.engine();
    if tree.is_instanced() || engine.is_instanced() {
        return Err(unsupported(
            "a two-level BVH (refit a mesh on the CPU: InstancedBvh::refit_mesh)",
        ));
    }
    if engine.has_wide() {
        return Err(unsupported(
            "the wide layout (upload without Traversal::Wide, or refit on the CPU: FlatBvh::refit)",
        ));
    }
    check_update_shape(engine.tree().shape, tree)?;
    let bad = |buffer, problem: String| Err(GpuError::BadBuffer { buffer, problem });
    if v.stride < 3 {
        return bad(
            "positions",
            format!("a stride of {} floats (at least 3)", v.stride),
        );
    }
    let need = (u64::from(v.vertices.max(1)) - 1) * u64::from(v.stride) * 4 + 12;
    if v.vertices == 0 || v.positions.size() < need {
        return bad(
            "positions",
            format!(
                "{} bytes for {} vertices of stride {} (needs {need})",
                v.positions.size(),
                v.vertices,
                v.stride
            ),
        );
    }
    let tris = tree.triangle_count() as u64;
    if let Some(i) = v.indices.filter(|i| i.size() < tris * 12) {
        return bad(
            "indices",
            format!(
                "{} bytes for {tris} triangles (needs {})",
                i.size(),
                tris * 12
            ),
        );
    }
    Ok(())
}

impl GpuRefit {
    /// Prepares refits of `bvh`, uploaded from `tree` (the same tree: its shape is
    /// checked), from the vertices `v` says. Errors name what does not fit: a two-level
    /// tree, the wide layout, another tree's shape, buffers too small.
    pub fn new(bvh: &GpuBvh, tree: &FlatBvh, v: RefitVertices<'_>) -> Result<GpuRefit, GpuError> {
        check(bvh, tree, &v)?;
        let ctx = bvh.context().clone();
        let (nodes, triangles, textures) = target_arrays(&ctx, bvh, tree)?;
        let pages = bvh.tree().pages;
        let entries: Vec<&'static str> = REFIT_STEPS.iter().map(|(e, _)| *e).collect();
        // One program per split: its page counts and size are in its text.
        let name = match pages.is_one() {
            true => "refit".to_string(),
            false => format!("refit {pages:?}"),
        };
        let pipelines = ctx.device_program(&name, || refit_source_for(pages), &entries)?;
        let device = ctx.device();
        let (order, runs) = levels(tree.nodes());
        let n_tris = tree.triangle_count() as u32;
        let max_dim = ctx.limits().max_compute_workgroups_per_dimension;
        // (step, first, count) of each dispatch.
        let mut plan = vec![(0, 0, n_tris), (1, 0, n_tris)];
        let mut first = 0;
        for r in runs.iter().filter(|&&r| r > 0) {
            plan.push((2, first, *r));
            first += r;
        }
        if textures.is_some() {
            plan.push((3, 0, tree.nodes().len() as u32));
        }
        let mut params = vec![0u8; plan.len() * PARAMS_STRIDE as usize];
        let mut grids = Vec::with_capacity(plan.len());
        for (k, &(_, first, count)) in plan.iter().enumerate() {
            let (x, y, row) = grid(u64::from(count), max_dim);
            grids.push((x, y));
            let p = RefitParams {
                first,
                count,
                row,
                stride: v.stride,
                vertices: v.vertices,
                triangles: n_tris,
                indexed: u32::from(v.indices.is_some()),
                pad: 0,
            };
            let at = k * PARAMS_STRIDE as usize;
            params[at..at + 32].copy_from_slice(bytemuck::bytes_of(&p));
        }
        use wgpu::BufferUsages as U;
        let params = init(device, "refit params", &params, U::UNIFORM);
        let order = init(
            device,
            "refit order",
            bytemuck::cast_slice(&order),
            U::STORAGE,
        );
        let no_indices = empty(device, "refit no indices", 16, U::STORAGE);
        let status = empty(
            device,
            "refit status",
            16,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let status_read = empty(device, "refit status read", 16, U::MAP_READ | U::COPY_DST);
        // The nodes as texels, for a BVH in textures (else never bound).
        let texel_bytes = textures
            .as_ref()
            .map_or(16, |_| tree.nodes().len() as u64 * 32);
        let node_texels = empty(
            device,
            "refit node texels",
            texel_bytes,
            U::STORAGE | U::COPY_SRC,
        );
        let resource = |b: u32, k: usize| match b {
            0 => wgpu::BindingResource::Buffer(wgpu::BufferBinding {
                buffer: &params,
                offset: k as u64 * PARAMS_STRIDE,
                size: std::num::NonZeroU64::new(32),
            }),
            3 => order.as_entire_binding(),
            4 => v.positions.as_entire_binding(),
            5 => v.indices.unwrap_or(&no_indices).as_entire_binding(),
            6 => status.as_entire_binding(),
            7 => node_texels.as_entire_binding(),
            // Binding 1 (the nodes) or 2 (the triangles), page `b / 8`.
            _ => {
                let array = if b % PAGE_BINDING_STRIDE == 1 {
                    &nodes
                } else {
                    &triangles
                };
                array[(b / PAGE_BINDING_STRIDE) as usize].as_entire_binding()
            }
        };
        // Each step's bindings, with the further pages of the tree's arrays it writes.
        let bound = |bindings: &[u32]| -> Vec<u32> {
            let mut out = bindings.to_vec();
            for (b, count) in [(1, pages.nodes), (2, pages.triangles)] {
                if bindings.contains(&b) {
                    out.extend((1..u32::from(count)).map(|p| b + PAGE_BINDING_STRIDE * p));
                }
            }
            out
        };
        let dispatches = ctx.scoped("preparing a refit on the device", || {
            plan.iter()
                .zip(&grids)
                .enumerate()
                .map(|(k, (&(step, _, _), &g))| {
                    let (entry, bindings) = REFIT_STEPS[step];
                    let entries: Vec<wgpu::BindGroupEntry<'_>> = bound(bindings)
                        .into_iter()
                        .map(|b| wgpu::BindGroupEntry {
                            binding: b,
                            resource: resource(b, k),
                        })
                        .collect();
                    let group = device.create_bind_group(&wgpu::BindGroupDescriptor {
                        label: Some(entry),
                        layout: &pipelines[step].get_bind_group_layout(0),
                        entries: &entries,
                    });
                    (step, group, g)
                })
                .collect::<Vec<_>>()
        })?;
        Ok(GpuRefit {
            pipelines,
            dispatches,
            status,
            status_read,
            nodes,
            triangles,
            pages,
            textures: textures.map(|t| (node_texels, t)),
            counts: (tree.nodes().len() as u64, u64::from(n_tris)),
            depth: tree.depth(),
            ctx,
        })
    }

    /// Dispatches a refit runs: the check, the corners, one per level of boxes, and the
    /// node texels for an upload in textures.
    pub fn dispatches(&self) -> usize {
        self.dispatches.len()
    }

    /// Records the refit into `enc`, after whatever moved the vertices: one compute pass
    /// (then, for an upload in textures, the copies over them). A bad vertex (not finite,
    /// or an index out of range) makes the whole refit write nothing; only
    /// [`GpuRefit::refit`] reads the outcome back and reports it.
    pub fn record(&self, enc: &mut wgpu::CommandEncoder) {
        self.record_timed(enc, None);
    }

    fn record_timed(&self, enc: &mut wgpu::CommandEncoder, queries: Option<&StepQueries>) {
        enc.clear_buffer(&self.status, 0, None);
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
                label: Some("refit"),
                timestamp_writes: queries.and_then(|q| q.writes("refit")),
            });
            for (step, group, (x, y)) in &self.dispatches {
                pass.set_pipeline(&self.pipelines[*step]);
                pass.set_bind_group(0, group, &[]);
                pass.dispatch_workgroups(*x, *y, 1);
            }
        }
        if let Some((node_texels, (nodes, triangles))) = &self.textures {
            copy_texels(enc, node_texels, nodes, self.counts.0 * 2);
            copy_texels(enc, &self.triangles[0], triangles, self.counts.1 * 3);
        }
        enc.copy_buffer_to_buffer(&self.status, 0, &self.status_read, 0, 16);
    }

    /// Runs the refit on `bvh` (the upload it was prepared for) and waits: `Ok` with its
    /// times, or the first bad triangle, named, with the tree left as it was. When the
    /// upload keeps a host copy (a CPU driver), the refitted tree is read back into it.
    pub fn refit(&self, bvh: &mut GpuBvh) -> Result<RefitTimes, GpuError> {
        let (device, queue) = (self.ctx.device(), self.ctx.queue());
        let queries = self
            .ctx
            .has_timestamps()
            .then(|| StepQueries::new(device, 1));
        let mut enc = device.create_command_encoder(&Default::default());
        self.record_timed(&mut enc, queries.as_ref());
        if let Some(q) = &queries {
            q.resolve(&mut enc);
        }
        let start = Instant::now();
        let mut maps = vec![(&self.status_read, 16)];
        maps.extend(queries.as_ref().map(|q| (&q.read, q.bytes())));
        submit_and_map(&self.ctx, "refitting on the device", enc, &maps)?;
        let status = self.read_status();
        let wall_ms = start.elapsed().as_secs_f64() * 1e3;
        let gpu_ms = match &queries {
            Some(q) => q.stages_ms(queue)?.first().map(|(_, ms)| *ms),
            None => None,
        };
        status?;
        let t = Instant::now();
        let kept = bvh.engine().keeps_host_copy();
        if kept {
            let tree = self.read_back()?;
            bvh.engine_mut().refitted_on_device(&tree)?;
        }
        Ok(RefitTimes {
            wall_ms,
            gpu_ms,
            dispatches: self.dispatches.len(),
            host_copy_ms: if kept {
                t.elapsed().as_secs_f64() * 1e3
            } else {
                0.0
            },
        })
    }

    /// The outcome of the last refit submitted (after it completed and its status buffer
    /// was mapped by [`GpuRefit::refit`]): `Ok`, or the first bad triangle, named.
    fn read_status(&self) -> Result<(), GpuError> {
        let mut words: Vec<u32> = Vec::new();
        let got = read_mapped(&self.status_read, 16, &mut words);
        self.status_read.unmap();
        got?;
        match words.first().copied().unwrap_or(0) {
            0 => Ok(()),
            s => {
                let code = u32::MAX - s;
                let (t, why) = (code / 4, code % 4);
                let problem = match why {
                    1 => format!("triangle {t}: a corner is NaN or infinite; nothing was refitted"),
                    _ => format!(
                        "triangle {t}: a vertex index is out of range; nothing was refitted"
                    ),
                };
                Err(GpuError::BadBuffer {
                    buffer: "positions",
                    problem,
                })
            }
        }
    }

    /// The tree as the device holds it now (after a refit: refitted), read back, so the
    /// CPU walks can trace it too.
    pub fn read_back(&self) -> Result<FlatBvh, GpuError> {
        let (nodes_bytes, tris_bytes) = (self.counts.0 * 32, self.counts.1 * 48);
        let enc = self
            .ctx
            .device()
            .create_command_encoder(&Default::default());
        let page = |element: u64| self.pages.per_page(element) * element;
        let mut sources = page_sources(&self.nodes, nodes_bytes, page(32));
        sources.extend(page_sources(&self.triangles, tris_bytes, page(48)));
        let bytes = read_after(&self.ctx, "reading a refitted tree back", enc, &sources)?;
        let (n, t) = bytes.split_at(nodes_bytes as usize);
        let nodes: Vec<FlatNode> = bytemuck::pod_collect_to_vec(n);
        let tris: Vec<FlatTriangle> = bytemuck::pod_collect_to_vec(t);
        Ok(FlatBvh::from_parts(nodes, tris, self.depth))
    }
}

#[cfg(test)]
mod tests {
    use super::levels;
    use bvhtrace_core::{BuildOptions, FlatBvh, Triangle};
    use glam::Vec3;

    /// Every node appears once, leaves first, and every interior node after both children.
    #[test]
    fn levels_order_children_before_parents() {
        let tris: Vec<Triangle> = (0..200)
            .map(|i| {
                let p = Vec3::new((i % 13) as f32, (i / 13) as f32, (i % 7) as f32 * 0.5);
                [p, p + Vec3::X, p + Vec3::Y]
            })
            .collect();
        let bvh = FlatBvh::build(&tris, &BuildOptions::default()).expect("builds");
        let (order, runs) = levels(bvh.nodes());
        assert_eq!(order.len(), bvh.nodes().len());
        assert_eq!(runs.iter().sum::<u32>() as usize, order.len());
        let mut run_of = vec![usize::MAX; order.len()];
        let mut at = 0;
        for (r, &len) in runs.iter().enumerate() {
            for &i in &order[at..at + len as usize] {
                assert_eq!(run_of[i as usize], usize::MAX, "node {i} twice");
                run_of[i as usize] = r;
            }
            at += len as usize;
        }
        assert!(
            order[..runs[0] as usize]
                .iter()
                .all(|&i| bvh.nodes()[i as usize].is_leaf())
        );
        for (i, n) in bvh.nodes().iter().enumerate().filter(|(_, n)| !n.is_leaf()) {
            for c in [i + 1, n.right_or_first as usize] {
                assert!(run_of[c] < run_of[i], "node {i} runs before its child {c}");
            }
        }
    }
}
