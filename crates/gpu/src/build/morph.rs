//! Morph targets on the device (`shaders/morph.wgsl`, the twin of
//! `bvhtrace_scene::morph_vertex`): a mesh's base positions and its targets' position
//! deltas are uploaded once; each frame its weights are written and its positions morphed
//! where they are traced, into a buffer a [`crate::GpuSkin`] skins
//! ([`crate::GpuSkin::after_morph`]) or a [`crate::GpuRefit`] reads
//! ([`GpuMorph::vertices`]).

use bvhtrace_engine::programs::{MORPH_STEP, MorphParams, morph_source};
use glam::Vec3;

use super::skin::VertexProgram;
use super::{empty, init};
use crate::{GpuContext, GpuError, RefitVertices};

/// One mesh with morph targets on the device: its base positions, its targets' deltas,
/// their weights, and the positions [`GpuMorph::record`] writes.
#[derive(Debug)]
pub struct GpuMorph {
    program: VertexProgram,
    weights: wgpu::Buffer,
    targets: u32,
}

impl GpuMorph {
    /// Uploads a mesh's base positions and its targets' position deltas, target by
    /// target (target `i`'s delta for vertex `v` at `i * base.len() + v`, as
    /// `bvhtrace_scene::Morph::position_deltas` holds them). The mesh must have at least
    /// one vertex and one target, and the deltas be finite, `targets` blocks of one per
    /// vertex.
    pub fn new(ctx: &GpuContext, base: &[Vec3], deltas: &[Vec3]) -> Result<GpuMorph, GpuError> {
        let n = base.len();
        let bad = |problem: String| GpuError::BadBuffer {
            buffer: "morph targets",
            problem,
        };
        if n == 0 || deltas.is_empty() || !deltas.len().is_multiple_of(n) {
            return Err(bad(format!(
                "{n} positions and {} deltas: one delta per vertex for each target, at least \
                 one vertex and one target",
                deltas.len()
            )));
        }
        if let Some(k) = deltas.iter().position(|d| !d.is_finite()) {
            return Err(bad(format!("delta {k} is not finite ({})", deltas[k])));
        }
        let targets = (deltas.len() / n) as u32;
        let device = ctx.device();
        let params = MorphParams {
            vertices: n as u32,
            targets,
            row: VertexProgram::row(ctx, n),
            pad: 0,
        };
        use wgpu::BufferUsages as U;
        let storage = |label, bytes: &[u8]| init(device, label, bytes, U::STORAGE);
        let params = init(
            device,
            "morph params",
            bytemuck::bytes_of(&params),
            U::UNIFORM,
        );
        let base = storage("morph base positions", bytemuck::cast_slice(base));
        let deltas = storage("morph deltas", bytemuck::cast_slice(deltas));
        let weights = empty(
            device,
            "morph weights",
            u64::from(targets) * 4,
            U::STORAGE | U::COPY_DST,
        );
        let inputs = [&params, &base, &deltas, &weights];
        let program = VertexProgram::new(ctx, "morph", (morph_source, MORPH_STEP), &inputs, n)?;
        Ok(GpuMorph {
            program,
            weights,
            targets,
        })
    }

    /// Writes the weights (one per target) for the next morph; another count, or a weight
    /// that is not finite, is an error naming it.
    pub fn set_weights(&self, weights: &[f32]) -> Result<(), GpuError> {
        let bad = |problem: String| GpuError::BadBuffer {
            buffer: "morph weights",
            problem,
        };
        if weights.len() != self.targets as usize {
            return Err(bad(format!(
                "{} weights for {} targets",
                weights.len(),
                self.targets
            )));
        }
        if let Some(i) = weights.iter().position(|w| !w.is_finite()) {
            return Err(bad(format!("weight {i} is not finite ({})", weights[i])));
        }
        let queue = self.program.output().0.queue();
        queue.write_buffer(&self.weights, 0, bytemuck::cast_slice(weights));
        Ok(())
    }

    /// Records the morph into `enc`: the positions from the weights last written.
    pub fn record(&self, enc: &mut wgpu::CommandEncoder) {
        self.program.record(enc);
    }

    /// The morphed positions as a refit reads them: packed `xyz`, one per vertex, with
    /// the mesh's triangles as `indices` (three per triangle, the builder's input order).
    pub fn vertices<'a>(&'a self, indices: Option<&'a wgpu::Buffer>) -> RefitVertices<'a> {
        self.program.vertices(indices)
    }

    /// The program, whose output a skin after it reads.
    pub(super) fn program(&self) -> &VertexProgram {
        &self.program
    }

    /// Morphs now (a submission of its own) and reads the positions back: for checks.
    pub fn morph_and_read(&self) -> Result<Vec<Vec3>, GpuError> {
        self.program.read_after(self.program.encoder(), true)
    }
}
