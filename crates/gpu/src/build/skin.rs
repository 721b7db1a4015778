//! Linear blend skinning on the device (`shaders/skin.wgsl`, the twin of
//! `bvhtrace_scene::skin_vertex`): a skinned mesh's bind pose, joints and weights are
//! uploaded once; each frame its joint matrices are written and its positions skinned
//! where they are traced, into a buffer a [`crate::GpuRefit`] reads
//! ([`GpuSkin::vertices`]).

use bvhtrace_kernels::build::{SKIN_STEP, SkinParams, skin_source};
use glam::{Mat4, Vec3};

use super::{empty, grid, init, read_after};
use crate::{GpuContext, GpuError, RefitVertices};

/// One skinned mesh on the device: its bind pose, joints and weights, its joint
/// matrices, and the positions [`GpuSkin::record`] writes.
#[derive(Debug)]
pub struct GpuSkin {
    ctx: GpuContext,
    pipeline: wgpu::ComputePipeline,
    group: wgpu::BindGroup,
    matrices: wgpu::Buffer,
    positions: wgpu::Buffer,
    vertices: u32,
    joints: u32,
    grid: (u32, u32),
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
        let n = bind.len();
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
        let pipeline = ctx
            .device_program("skin", skin_source, &[SKIN_STEP.0])?
            .swap_remove(0);
        let device = ctx.device();
        let (x, y, row) = grid(n as u64, ctx.limits().max_compute_workgroups_per_dimension);
        let params = SkinParams {
            vertices: n as u32,
            joints,
            row,
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
        let bind = storage("skin bind pose", bytemuck::cast_slice(bind));
        let js = storage("skin joints", bytemuck::cast_slice(&wide));
        let ws = storage("skin weights", bytemuck::cast_slice(vertex_weights));
        let matrices = empty(
            device,
            "skin matrices",
            u64::from(joints) * 64,
            U::STORAGE | U::COPY_DST,
        );
        let positions = empty(
            device,
            "skinned positions",
            n as u64 * 12,
            U::STORAGE | U::COPY_SRC | U::COPY_DST,
        );
        let buffers = [&params, &bind, &js, &ws, &matrices, &positions];
        let group = ctx.scoped("preparing a skin on the device", || {
            let entries: Vec<wgpu::BindGroupEntry<'_>> = SKIN_STEP
                .1
                .iter()
                .map(|&b| wgpu::BindGroupEntry {
                    binding: b,
                    resource: buffers[b as usize].as_entire_binding(),
                })
                .collect();
            device.create_bind_group(&wgpu::BindGroupDescriptor {
                label: Some("skin"),
                layout: &pipeline.get_bind_group_layout(0),
                entries: &entries,
            })
        })?;
        Ok(GpuSkin {
            ctx: ctx.clone(),
            pipeline,
            group,
            matrices,
            positions,
            vertices: n as u32,
            joints,
            grid: (x, y),
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
        self.ctx
            .queue()
            .write_buffer(&self.matrices, 0, bytemuck::cast_slice(&cols));
        Ok(())
    }

    /// Records the skinning into `enc`: the positions from the matrices last written.
    pub fn record(&self, enc: &mut wgpu::CommandEncoder) {
        let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor {
            label: Some("skin"),
            timestamp_writes: None,
        });
        pass.set_pipeline(&self.pipeline);
        pass.set_bind_group(0, &self.group, &[]);
        pass.dispatch_workgroups(self.grid.0, self.grid.1, 1);
    }

    /// The skinned positions as a refit reads them: packed `xyz`, one per vertex, with the
    /// mesh's triangles as `indices` (three per triangle, the builder's input order).
    pub fn vertices<'a>(&'a self, indices: Option<&'a wgpu::Buffer>) -> RefitVertices<'a> {
        RefitVertices {
            positions: &self.positions,
            stride: 3,
            vertices: self.vertices,
            indices,
        }
    }

    /// Skins now (a submission of its own) and reads the positions back: for checks.
    pub fn skin_and_read(&self) -> Result<Vec<Vec3>, GpuError> {
        let mut enc = self
            .ctx
            .device()
            .create_command_encoder(&Default::default());
        self.record(&mut enc);
        let source = [(&self.positions, u64::from(self.vertices) * 12)];
        let bytes = read_after(&self.ctx, "skinning on the device", enc, &source)?;
        Ok(bytemuck::pod_collect_to_vec(&bytes))
    }
}
