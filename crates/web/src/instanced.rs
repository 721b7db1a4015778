//! Instances for JavaScript: meshes placed by transforms in two levels (a top tree over
//! the instances, each mesh's tree once however often it is placed), traced by the CPU
//! layout's two-level walks in WebAssembly, which answer as the flattened scene would.

use bvhtrace_core::{FlatBvh, Hit, Instance, MISS, Query};
use bvhtrace_cpu::{CpuBvh, RayScratch};
use glam::{Affine3A, Mat4};
use js_sys::{Object, Uint32Array};
use wasm_bindgen::prelude::*;

use crate::bvh::{Asked, Bvh, TraceOptionsArg, err, hit_of, hits_out, one_ray, rays, set};

#[wasm_bindgen]
extern "C" {
    /// `InstancedHits`.
    #[wasm_bindgen(typescript_type = "InstancedHits")]
    pub type InstancedHitsOut;
    /// `InstancedHit`, or undefined.
    #[wasm_bindgen(typescript_type = "InstancedHit | undefined")]
    pub type InstancedHitOut;
}

/// Meshes placed by transforms (Embree's instances, three.js's `InstancedMesh`): add each
/// mesh once (`addMesh`, from a `Bvh`), place it as often as needed (`addInstance`, a
/// column-major 4x4 matrix such as three.js's `Matrix4.elements`), then trace. Moving the
/// instances (`setTransforms`) keeps the meshes' trees. Call `free()` when done.
#[wasm_bindgen]
#[derive(Default)]
pub struct InstancedBvh {
    meshes: Vec<FlatBvh>,
    instances: Vec<Instance>,
    built: Option<(bvhtrace_core::InstancedBvh, CpuBvh)>,
    scratch: RayScratch,
}

/// A column-major 4x4 matrix as an object-to-world transform: 16 numbers whose last row is
/// 0, 0, 0, 1 (an affine transform), else an error naming the instance.
fn affine(m: &[f32], instance: usize) -> Result<Affine3A, JsError> {
    let Ok(cols) = <[f32; 16]>::try_from(m) else {
        return Err(err(format!(
            "instance {instance}: a transform is 16 numbers (a column-major 4x4 matrix), not {}",
            m.len()
        )));
    };
    if [cols[3], cols[7], cols[11], cols[15]] != [0.0, 0.0, 0.0, 1.0] {
        return Err(err(format!(
            "instance {instance}: the transform's last row is {:?}, not 0, 0, 0, 1 (not affine)",
            [cols[3], cols[7], cols[11], cols[15]]
        )));
    }
    Ok(Affine3A::from_mat4(Mat4::from_cols_array(&cols)))
}

impl InstancedBvh {
    /// The two levels, built now if an instance or mesh was added since.
    fn build(&mut self) -> Result<(), JsError> {
        if self.built.is_none() {
            let two = bvhtrace_core::InstancedBvh::new(self.meshes.clone(), self.instances.clone())
                .map_err(err)?;
            let cpu = CpuBvh::from_flat(two.bvh()).map_err(err)?;
            self.built = Some((two, cpu));
        }
        Ok(())
    }
}

#[wasm_bindgen]
impl InstancedBvh {
    /// No meshes and no instances yet.
    #[wasm_bindgen(constructor)]
    pub fn new() -> InstancedBvh {
        InstancedBvh::default()
    }

    /// Adds `bvh`'s mesh (its tree is copied: `bvh` stays usable and must still be freed)
    /// and returns its index for `addInstance`.
    #[wasm_bindgen(js_name = addMesh)]
    pub fn add_mesh(&mut self, bvh: &Bvh) -> u32 {
        self.meshes.push(bvh.flat.clone());
        self.built = None;
        (self.meshes.len() - 1) as u32
    }

    /// Places mesh `mesh` by `transform` (16 numbers, column-major, last row 0, 0, 0, 1)
    /// and returns the instance's index, which hits report.
    #[wasm_bindgen(js_name = addInstance)]
    pub fn add_instance(&mut self, mesh: u32, transform: &[f32]) -> Result<u32, JsError> {
        let index = self.instances.len();
        if mesh as usize >= self.meshes.len() {
            return Err(err(format!(
                "instance {index}: mesh {mesh} was not added ({} meshes)",
                self.meshes.len()
            )));
        }
        self.instances
            .push(Instance::new(mesh, affine(transform, index)?));
        self.built = None;
        Ok(index as u32)
    }

    /// Instances placed.
    #[wasm_bindgen(getter, js_name = instanceCount)]
    pub fn instance_count(&self) -> u32 {
        self.instances.len() as u32
    }

    /// Moves every instance: 16 numbers per instance, in the order they were added. The
    /// meshes' trees are kept and the top tree rebuilt (the CPU layout is converted again,
    /// the meshes' parts too). An unusable transform (not affine, NaN, not invertible) is
    /// an error naming the instance, and moves nothing.
    #[wasm_bindgen(js_name = setTransforms)]
    pub fn set_transforms(&mut self, transforms: &[f32]) -> Result<(), JsError> {
        if transforms.len() != 16 * self.instances.len() {
            return Err(err(format!(
                "{} numbers for {} instances: 16 each",
                transforms.len(),
                self.instances.len()
            )));
        }
        let moved = transforms
            .chunks_exact(16)
            .enumerate()
            .map(|(i, m)| affine(m, i))
            .collect::<Result<Vec<_>, _>>()?;
        if let Some((two, cpu)) = &mut self.built {
            two.set_transforms(&moved).map_err(err)?;
            *cpu = CpuBvh::from_flat(two.bvh()).map_err(err)?;
        }
        for (inst, m) in self.instances.iter_mut().zip(moved) {
            inst.transform = m;
        }
        Ok(())
    }

    /// Traces rays from `origins` along `directions` (three floats per ray each) through
    /// every instance, as `Bvh.intersect` does; each hit also says its `instance` and
    /// its triangle in the mesh (`meshPrimitive`). `primitive` numbers the triangles of
    /// every instance in turn.
    pub fn intersect(
        &mut self,
        origins: &[f32],
        directions: &[f32],
        options: Option<TraceOptionsArg>,
    ) -> Result<InstancedHitsOut, JsError> {
        let asked = Asked::of(options.as_ref())?;
        let rays = rays(origins, directions, asked)?;
        let start = web_time::Instant::now();
        self.build()?;
        let Some((two, cpu)) = &self.built else {
            return Err(err("the instances were not built"));
        };
        let hits = bvhtrace_cpu::trace_rays(cpu, &rays, asked.query);
        let ms = start.elapsed().as_secs_f64() * 1e3;
        let out: Object = hits_out(&hits, Bvh::wasm_name(), ms)?.unchecked_into();
        let (inst, local): (Vec<u32>, Vec<u32>) = hits
            .iter()
            .map(|h| two.locate(h.prim).unwrap_or((MISS, MISS)))
            .unzip();
        set(&out, "instance", &Uint32Array::from(&inst[..]))?;
        set(&out, "meshPrimitive", &Uint32Array::from(&local[..]))?;
        Ok(out.unchecked_into())
    }

    /// The closest hit of one ray through every instance (six numbers, as
    /// `Bvh.raycastFirst`), with its `instance` and `meshPrimitive`, or undefined.
    #[allow(clippy::too_many_arguments)]
    #[wasm_bindgen(js_name = raycastFirst)]
    pub fn raycast_first(
        &mut self,
        ox: f32,
        oy: f32,
        oz: f32,
        dx: f32,
        dy: f32,
        dz: f32,
        near: Option<f32>,
        far: Option<f32>,
    ) -> Result<InstancedHitOut, JsError> {
        let ray = one_ray([ox, oy, oz], [dx, dy, dz], near, far);
        self.build()?;
        let Some((two, cpu)) = &self.built else {
            return Err(err("the instances were not built"));
        };
        let h: Hit = bvhtrace_cpu::trace_ray_in(cpu, &ray, Query::Closest, &mut self.scratch);
        // A miss code is no instance's primitive.
        let Some((instance, local)) = two.locate(h.prim) else {
            return Ok(JsValue::UNDEFINED.unchecked_into());
        };
        let out: Object = hit_of(&ray, &h).unchecked_into();
        set(&out, "instance", &JsValue::from(instance))?;
        set(&out, "meshPrimitive", &JsValue::from(local))?;
        Ok(out.unchecked_into())
    }
}
