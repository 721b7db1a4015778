//! A test device for bvhtrace's engine: [`MockDevice`] implements the engine's device trait
//! ([`DeviceApi`]) with every array held as bytes, and its kernels are the CPU twins of
//! `bvhtrace_core`, walking a tree remade from exactly the bytes the engine uploaded (so a
//! tree that traces right here went up whole, with every array its walks read). Its limits
//! and features are the caller's ([`MockDevice::with_limits`]): a front end's handling of a
//! device too small for a scene is tested without one.
//!
//! ```
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! use bvhtrace_core::{BuildOptions, FlatBvh, Ray, TraceOptions, Traversal, trace_rays};
//! use bvhtrace_engine::{Tracer, UploadOptions};
//! use bvhtrace_mock::{MockBvh, MockDevice};
//! use glam::Vec3;
//!
//! let tris = vec![[Vec3::new(-1.0, -1.0, 0.0), Vec3::new(1.0, -1.0, 0.0), Vec3::new(0.0, 1.0, 0.0)]];
//! let bvh = FlatBvh::build(&tris, &BuildOptions::default())?;
//! let mock = MockBvh::upload(&MockDevice::new(), &bvh, &UploadOptions::all())?;
//! let rays = [Ray::new(Vec3::new(0.0, 0.0, 5.0), Vec3::NEG_Z)];
//! let opts = TraceOptions::closest(Traversal::Stackless);
//! assert_eq!(mock.trace(&rays, &opts)?.hits, trace_rays(&bvh, &rays, &opts).hits);
//! # Ok(()) }
//! ```
//!
//! It is the proof that a backend is one crate: the front door opens it as
//! `bvhtrace::Backend::Mock`, and the conformance and stress suites trace on it. Not fast,
//! and not for tracing on the CPU: that is `bvhtrace::Backend::Cpu`.
#![warn(missing_docs)]

use std::sync::Arc;

use bvhtrace_core::{FlatBvh, FlatInstance, MaskTables, Ray, TraceOptions, TracePhases, WideBvh};
use bvhtrace_engine::engine::{
    ArrayWrite, ArraysLayout, BackendFeatures, Batch, BatchOut, BatchTimes, DeviceApi, HasEngine,
    ScratchPlan, UploadedTree,
};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::upload::{ArrayRole, DeviceArray};
use bvhtrace_engine::walks::{Layout, walk};
use bvhtrace_engine::{DriverTuning, Engine, KernelKey, TraceError, UploadOptions, UploadStats};

/// The backend name of the mock's tracers ([`bvhtrace_engine::Tracer::backend`]).
pub const MOCK_BACKEND: &str = "mock";

/// A device of bytes: its limits, its measures and what its kernels read.
#[derive(Clone, Debug, PartialEq)]
pub struct MockDevice {
    limits: DeviceLimits,
    tuning: DriverTuning,
    features: BackendFeatures,
}

impl Default for MockDevice {
    fn default() -> Self {
        MockDevice::new()
    }
}

impl MockDevice {
    /// A device with WebGPU's default limits (128 MiB a binding, 8192 texels a side), the
    /// tree in buffers only (no texture storage), f64 triangle tests, no trip budget.
    pub fn new() -> MockDevice {
        MockDevice {
            limits: DeviceLimits {
                max_storage_buffer_binding_size: 128 << 20,
                max_buffer_size: 256 << 20,
                max_compute_workgroups_per_dimension: 65_535,
                min_storage_buffer_offset_alignment: 256,
                max_texture_dimension_2d: 8192,
                max_storage_buffers_per_shader_stage: 8,
            },
            tuning: DriverTuning::GPU,
            features: BackendFeatures {
                textures: false,
                vertex_attributes: false,
                f64: true,
            },
        }
    }

    /// The same device with these limits.
    pub fn with_limits(self, limits: DeviceLimits) -> MockDevice {
        MockDevice { limits, ..self }
    }

    /// The same device with these measures (a trip budget keeps a host copy; the mock's
    /// kernels never give a ray up).
    pub fn with_tuning(self, tuning: DriverTuning) -> MockDevice {
        MockDevice { tuning, ..self }
    }

    /// Its name, as a tracer on it says it.
    pub fn name(&self) -> String {
        "mock (the CPU twins over uploaded bytes)".to_string()
    }
}

/// The uploaded arrays, as bytes, and the trees the kernels walk, remade from them after
/// every write.
#[derive(Debug, Default)]
pub struct MockArrays {
    /// Each array (each page of one split over bindings) by role and page.
    bytes: Vec<((ArrayRole, u8), Vec<u8>)>,
    /// The binary layout: nodes, triangles, escape links, instances, masks.
    binary: Option<FlatBvh>,
    /// The wide layout, with a tree of its instances and masks beside it for the walk.
    wide: Option<(FlatBvh, WideBvh)>,
}

impl MockArrays {
    /// The bytes of `role`, its pages joined in order, when uploaded.
    fn get(&self, role: ArrayRole) -> Option<Vec<u8>> {
        let mut pages: Vec<_> = (self.bytes.iter())
            .filter(|((r, _), _)| *r == role)
            .collect();
        pages.sort_by_key(|((_, page), _)| *page);
        let first = pages.first()?;
        let mut out = first.1.clone();
        for (_, b) in &pages[1..] {
            out.extend_from_slice(b);
        }
        Some(out)
    }

    /// The elements of `role`, when uploaded.
    fn elements<T: bytemuck::Pod>(&self, role: ArrayRole) -> Vec<T> {
        self.get(role)
            .map_or_else(Vec::new, |b| bytemuck::pod_collect_to_vec(&b))
    }

    /// The tables of `role`'s mask words, when uploaded.
    fn masks(&self, role: ArrayRole) -> Result<Option<Arc<MaskTables>>, TraceError> {
        let Some(bytes) = self.get(role) else {
            return Ok(None);
        };
        let words: Vec<u32> = bytemuck::pod_collect_to_vec(&bytes);
        let tables = MaskTables::from_words(&words).map_err(|problem| TraceError::BadBuffer {
            buffer: role.name(false),
            problem,
        })?;
        Ok(Some(Arc::new(tables)))
    }

    /// A tree of `instances` (the top level's node count the kernels take, `2n - 1`) and
    /// `masks`, over `nodes` and `triangles`.
    fn tree(
        nodes: Vec<bvhtrace_core::FlatNode>,
        triangles: Vec<bvhtrace_core::FlatTriangle>,
        instances: Vec<FlatInstance>,
        masks: Option<Arc<MaskTables>>,
    ) -> Result<FlatBvh, TraceError> {
        let mut bvh = FlatBvh::from_parts(nodes, triangles, 0);
        let parts = bvh.parts_mut();
        *parts.top_nodes = (2 * instances.len() as u32).saturating_sub(1);
        *parts.instances = instances;
        (bvh.set_masks(masks)).map_err(|problem| TraceError::BadBuffer {
            buffer: "alpha masks",
            problem,
        })?;
        Ok(bvh)
    }

    /// Remakes the trees from the bytes.
    fn remake(&mut self) -> Result<(), TraceError> {
        self.binary = match self.get(ArrayRole::Nodes) {
            None => None,
            Some(_) => {
                let mut bvh = MockArrays::tree(
                    self.elements(ArrayRole::Nodes),
                    self.elements(ArrayRole::Triangles),
                    self.elements(ArrayRole::Instances),
                    self.masks(ArrayRole::Masks)?,
                )?;
                if self.get(ArrayRole::Escapes).is_some() {
                    bvh.set_escapes(self.elements(ArrayRole::Escapes));
                }
                Some(bvh)
            }
        };
        self.wide = match self.get(ArrayRole::WideNodes) {
            None => None,
            Some(_) => {
                // The instances in the wide top level's order, which the masks' bases
                // follow too: the walk is told each instance's place in this order.
                let instances: Vec<FlatInstance> = self.elements(ArrayRole::WideInstances);
                let host = MockArrays::tree(
                    Vec::new(),
                    Vec::new(),
                    instances.clone(),
                    self.masks(ArrayRole::WideMasks)?,
                )?;
                let wide = WideBvh {
                    nodes: self.elements(ArrayRole::WideNodes),
                    triangles: self.elements(ArrayRole::WideTriangles),
                    instance_order: (0..instances.len() as u32).collect(),
                    top_nodes: instances.first().map_or(0, |i| i.root),
                    depth: 0,
                    instances,
                };
                Some((host, wide))
            }
        };
        Ok(())
    }

    /// The binary tree or the wide one a kernel of `key` walks, traced on `rays`.
    fn trace(
        &self,
        key: &KernelKey,
        rays: &[Ray],
    ) -> Result<bvhtrace_core::TraceOutput, TraceError> {
        let opts: TraceOptions = key.options();
        let missing = |layout| TraceError::Device {
            during: "tracing on the mock",
            message: format!("the {layout} layout was not uploaded"),
        };
        Ok(match walk(key.traversal).layout {
            Layout::Binary => {
                let bvh = self.binary.as_ref().ok_or_else(|| missing("binary"))?;
                bvhtrace_core::trace_rays_in(bvh, None, rays, &opts, None)
            }
            Layout::Wide => {
                let (host, wide) = self.wide.as_ref().ok_or_else(|| missing("wide"))?;
                bvhtrace_core::trace_rays_in(host, Some(wide), rays, &opts, None)
            }
        })
    }
}

impl DeviceApi for MockDevice {
    type Arrays = MockArrays;
    type Scratch = ();
    type Submitted = (bvhtrace_core::TraceOutput, f64);

    fn name(&self) -> &'static str {
        MOCK_BACKEND
    }

    fn device_name(&self) -> String {
        self.name()
    }

    fn limits(&self) -> &DeviceLimits {
        &self.limits
    }

    fn tuning(&self) -> &DriverTuning {
        &self.tuning
    }

    fn has_timestamps(&self) -> bool {
        false
    }

    fn features(&self) -> BackendFeatures {
        self.features
    }

    fn prepare_kernel(&self, key: KernelKey) -> Result<(), TraceError> {
        self.features.check(&key, || self.name())
    }

    fn create_arrays(
        &self,
        _: ArraysLayout,
        arrays: &[DeviceArray<'_>],
    ) -> Result<MockArrays, TraceError> {
        let mut made = MockArrays {
            bytes: (arrays.iter())
                .map(|a| ((a.role, a.page), a.bytes.to_vec()))
                .collect(),
            ..MockArrays::default()
        };
        made.remake()?;
        Ok(made)
    }

    fn write_arrays(
        &self,
        arrays: &mut MockArrays,
        _: ArraysLayout,
        writes: &[ArrayWrite<'_>],
    ) -> Result<(), TraceError> {
        for w in writes {
            let a = &w.array;
            let at = (a.role, a.page);
            match arrays.bytes.iter_mut().find(|(r, _)| *r == at) {
                Some((_, bytes)) if !w.replace => bytes[..a.bytes.len()].copy_from_slice(&a.bytes),
                Some((_, bytes)) => *bytes = a.bytes.to_vec(),
                None => arrays.bytes.push((at, a.bytes.to_vec())),
            }
        }
        arrays.remake()
    }

    fn create_scratch(&self, _: &ScratchPlan) -> Result<(), TraceError> {
        Ok(())
    }

    // The CPU twins answer at once, when submitted.
    fn submit_batch(
        &self,
        arrays: &MockArrays,
        _: &(),
        batch: Batch<'_>,
    ) -> Result<(bvhtrace_core::TraceOutput, f64), TraceError> {
        // Nothing to upload or read back: the twins' time is the device's.
        let start = web_time::Instant::now();
        let out = arrays.trace(&batch.key, batch.rays)?;
        Ok((out, start.elapsed().as_secs_f64() * 1e3))
    }

    async fn finish_batch<'a>(
        &'a self,
        _: &'a (),
        (done, device_ms): (bvhtrace_core::TraceOutput, f64),
        out: BatchOut<'a>,
    ) -> Result<BatchTimes, TraceError> {
        out.hits.extend(done.hits);
        if let Some(c) = out.counters {
            c.extend(done.counters.unwrap_or_default());
        }
        let phases = TracePhases {
            device_ms,
            ..TracePhases::default()
        };
        Ok(BatchTimes {
            gpu_ms: None,
            phases,
        })
    }
}

/// A tree uploaded to a [`MockDevice`]: the engine every device backend shares, over bytes.
/// A [`bvhtrace_engine::Tracer`].
#[derive(Debug)]
pub struct MockBvh {
    engine: Engine<MockDevice>,
}

impl HasEngine for MockBvh {
    type Device = MockDevice;
    fn engine(&self) -> &Engine<MockDevice> {
        &self.engine
    }
    fn engine_mut(&mut self) -> &mut Engine<MockDevice> {
        &mut self.engine
    }
}

impl MockBvh {
    /// Uploads `bvh` as `opts` says, by the rules every backend follows
    /// ([`Engine::upload`]), to `device`'s bytes.
    pub fn upload(
        device: &MockDevice,
        bvh: &FlatBvh,
        opts: &UploadOptions,
    ) -> Result<MockBvh, TraceError> {
        Ok(MockBvh {
            engine: Engine::upload(device.clone(), bvh, opts)?,
        })
    }

    /// What the upload holds.
    pub fn tree(&self) -> &UploadedTree {
        self.engine.tree()
    }

    /// What the upload holds and cost.
    pub fn stats(&self) -> &UploadStats {
        self.engine.stats()
    }
}
