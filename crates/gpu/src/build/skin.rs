//! Linear blend skinning on the device (`shaders/skin.wgsl`, the twin of
//! `bvhtrace_scene::skin_vertex`): a skinned mesh's bind pose, joints and weights are
//! uploaded once; each frame its joint matrices are written and its positions skinned
//! where they are traced, into a buffer a [`crate::GpuRefit`] reads
//! ([`GpuSkin::vertices`]). The bind pose can be what a [`GpuMorph`] writes
//! ([`GpuSkin::after_morph`]): morph targets first, then the skin, as glTF says.

use bvhtrace_engine::programs::{SKIN_STEP, SkinParams, Step, skin_source};
use glam::{Mat4, Vec3};

use super::{empty, grid, init, read_after};
use crate::{GpuContext, GpuError, GpuMorph, RefitVertices};

/// One skinned mesh on the device: its bind pose, joints and weights, its joint
/// matrices, and the positions [`GpuSkin::record`] writes.
#[derive(Debug)]
pub struct GpuSkin {
    program: VertexProgram,
    matrices: wgpu::Buffer,
    joints: u32,
}

/// One compute program over a mesh's vertices, bound once, and the positions it writes
/// (packed `xyz`, its last binding): the morph and the skin.
#[derive(Debug)]
pub(super) struct VertexProgram {
    ctx: GpuContext,
    name: &'static str,
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    grid: (u32, u32),
    positions: wgpu::Buffer,
    vertices: u32,
}

impl VertexProgram {
    /// Compiles (or takes from the cache) program `name`, makes its output positions and
    /// binds `inputs` and them (indexed by binding, the output last) to the bindings
    /// `step` lists, for `vertices` invocations.
    pub(super) fn new(
        ctx: &GpuContext,
        name: &'static str,
        (source, step): (fn() -> String, Step),
        inputs: &[&wgpu::Buffer],
        vertices: usize,
    ) -> Result<VertexProgram, GpuError> {
        let pipeline = ctx.device_program(name, source, &[step.0])?.swap_remove(0);
        let max = ctx.limits().max_compute_workgroups_per_dimension;
        let (x, y, _) = grid(vertices as u64, max);
        use wgpu::BufferUsages as U;
        let usage = U::STORAGE | U::COPY_SRC | U::COPY_DST;
        let positions = empty(ctx.device(), name, vertices as u64 * 12, usage);
        let buffers: Vec<&wgpu::Buffer> = inputs.iter().copied().chain([&positions]).collect();
        let group = ctx.scoped("binding a vertex program on the device", || {
            let entries: Vec<wgpu::BindGroupEntry<'_>> = (step.1.iter())
                .map(|&b| wgpu::BindGroupEntry {
                    binding: b,
                    resource: buffers[b as usize].as_entire_binding(),
                })
                .collect();
            ctx.device().create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some(name),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            })
        })?;
        Ok(VertexProgram {
            ctx: ctx.clone(),
            name,
            pipeline,
            group,
            grid: (x, y),
            positions,
            vertices: vertices as u32,
        })
    }

    /// The invocations per row of the dispatch grid for `vertices` (the programs' `row`).
    pub(super) fn row(ctx: &GpuContext, vertices: usize) -> u32 {
        grid(
            vertices as u64,
            ctx.limits().max_compute_workgroups_per_dimension,
        )
        .2
    }

    /// Its context, the positions it writes and their count.
    pub(super) fn output(&self) -> (&GpuContext, &wgpu::Buffer, usize) {
        (&self.ctx, &self.positions, self.vertices as usize)
    }

    /// Records the dispatch into `enc`.
    pub(super) fn record(&self, enc: &mut wgpu::CommandEncoder) {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some(self.name),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.group, &[]);
        pass.dispatch_workgroups(self.grid.0, self.grid.1, 1);
    }

    /// The positions as a refit reads them, with the mesh's triangles as `indices`.
    pub(super) fn vertices<'a>(&'a self, indices: Option<&'a wgpu::Buffer>) -> RefitVertices<'a> {
        RefitVertices {
            positions: &self.positions,
            stride: 3,
            vertices: self.vertices,
            indices,
        }
    }

    /// Submits `enc` and reads the positions back (`record_self`: this program recorded
    /// into it first).
    pub(super) fn read_after(
        &self,
        mut enc: wgpu::CommandEncoder,
        record_self: bool,
    ) -> Result<Vec<Vec3>, GpuError> {
        if record_self {
            self.record(&mut enc);
        }
        let source = [(&self.positions, u64::from(self.vertices) * 12)];
        let bytes = read_after(&self.ctx, "moving vertices on the device", enc, &source)?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }

    /// A new encoder on its device.
    pub(super) fn encoder(&self) -> wgpu::CommandEncoder {
        self.ctx
            .device()
            .create_command_encoder(&Default::default())
    }
}

impl GpuSkin {
    /// Uploads a skinned mesh: per vertex its bind-pose position, four joints (indices
    /// into the `joints` matrices [`GpuSkin::set_matrices`] writes) and their weights.
    /// The arrays must have one entry per vertex, and the mesh at least one vertex and
    /// one joint.
    pub fn new(
        ctx: &GpuContext,
        bind: &[Vec3],
        vertex_joints: &[[u16; 4]],
        vertex_weights: &[[f32; 4]],
        joints: u32,
    ) -> Result<GpuSkin, GpuError> {
        let usage = wgpu::BufferUsages::STORAGE;
        let buffer = init(
            ctx.device(),
            "skin bind pose",
            bytemuck::cast_slice(bind),
            usage,
        );
        Self::with_bind(
            ctx,
            buffer,
            bind.len(),
            vertex_joints,
            vertex_weights,
            joints,
        )
    }

    /// A skin whose bind pose is what `morph` writes: record the morph before the skin
    /// ([`GpuSkin::record`] after [`GpuMorph::record`]). The same arrays as
    /// [`GpuSkin::new`], one entry per vertex of the morphed mesh.
    pub fn after_morph(
        morph: &GpuMorph,
        vertex_joints: &[[u16; 4]],
        vertex_weights: &[[f32; 4]],
        joints: u32,
    ) -> Result<GpuSkin, GpuError> {
        let (ctx, buffer, n) = morph.program().output();
        Self::with_bind(
            ctx,
            buffer.clone(),
            n,
            vertex_joints,
            vertex_weights,
            joints,
        )
    }

    /// [`GpuSkin::new`] over a bind pose already on the device: `n` packed positions.
    fn with_bind(
        ctx: &GpuContext,
        bind: wgpu::Buffer,
        n: usize,
        vertex_joints: &[[u16; 4]],
        vertex_weights: &[[f32; 4]],
        joints: u32,
    ) -> Result<GpuSkin, GpuError> {
        if n == 0 || joints == 0 || vertex_joints.len() != n || vertex_weights.len() != n {
            return Err(GpuError::BadBuffer {
                buffer: "skin",
                problem: format!(
                    "{n} positions, {} joint sets, {} weight sets and {joints} joints: one set \
                     per vertex, at least one vertex and one joint",
                    vertex_joints.len(),
                    vertex_weights.len()
                ),
            });
        }
        let device = ctx.device();
        let params = SkinParams {
            vertices: n as u32,
            joints,
            row: VertexProgram::row(ctx, n),
            pad: 0,
        };
        use wgpu::BufferUsages as U;
        let wide: Vec<[u32; 4]> = vertex_joints.iter().map(|j| j.map(u32::from)).collect();
        let storage = |label, bytes: &[u8]| init(device, label, bytes, U::STORAGE);
        let params = init(
            device,
            "skin params",
            bytemuck::bytes_of(&params),
            U::UNIFORM,
        );
        let js = storage("skin joints", bytemuck::cast_slice(&wide));
        let ws = storage("skin weights", bytemuck::cast_slice(vertex_weights));
        let matrices = empty(
            device,
            "skin matrices",
            u64::from(joints) * 64,
            U::STORAGE | U::COPY_DST,
        );
        let inputs = [&params, &bind, &js, &ws, &matrices];
        let program = VertexProgram::new(ctx, "skin", (skin_source, SKIN_STEP), &inputs, n)?;
        Ok(GpuSkin {
            program,
            matrices,
            joints,
        })
    }

    /// Writes the joint matrices (`joint_world * inverse_bind`, one per joint) for the
    /// next skinning; a count other than the mesh's joints, or a matrix that is not
    /// finite, is an error naming it.
    pub fn set_matrices(&self, matrices: &[Mat4]) -> Result<(), GpuError> {
        let bad = |problem: String| GpuError::BadBuffer {
            buffer: "skin matrices",
            problem,
        };
        if matrices.len() != self.joints as usize {
            return Err(bad(format!(
                "{} matrices for {} joints",
                matrices.len(),
                self.joints
            )));
        }
        if let Some(j) = matrices.iter().position(|m| !m.is_finite()) {
            return Err(bad(format!("joint {j}'s matrix is not finite")));
        }
        let cols: Vec<[f32; 16]> = matrices.iter().map(Mat4::to_cols_array).collect();
        let queue = self.program.output().0.queue();
        queue.write_buffer(&self.matrices, 0, bytemuck::cast_slice(&cols));
        Ok(())
    }

    /// Records the skinning into `enc`: the positions from the matrices last written.
    pub fn record(&self, enc: &mut wgpu::CommandEncoder) {
        self.program.record(enc);
    }

    /// The skinned positions as a refit reads them: packed `xyz`, one per vertex, with the
    /// mesh's triangles as `indices` (three per triangle, the builder's input order).
    pub fn vertices<'a>(&'a self, indices: Option<&'a wgpu::Buffer>) -> RefitVertices<'a> {
        self.program.vertices(indices)
    }

    /// Skins now (a submission of its own) and reads the positions back: for checks.
    pub fn skin_and_read(&self) -> Result<Vec<Vec3>, GpuError> {
        self.program.read_after(self.program.encoder(), true)
    }

    /// Submits `enc` (with a morph and this skin recorded into it, say) and reads the
    /// skinned positions back: for checks.
    pub fn read_after(&self, enc: wgpu::CommandEncoder) -> Result<Vec<Vec3>, GpuError> {
        self.program.read_after(enc, false)
    }
}
