//! The engine's rules on a device of bytes: a mock [`Backend`] that keeps each array's
//! bytes and logs every write, so that what the engine decides (which arrays, which
//! errors, what an update writes, how a batch is split, which rays are finished) is seen
//! apart from any GPU. Every device backend runs these same rules.

use std::sync::Mutex;

use bvhtrace_core::{
    BuildOptions, FlatBvh, Hit, INCOMPLETE, Instance, InstancedBvh, Ray, TraceOptions, TracePhases,
    Traversal, Triangle, trace_rays,
};
use bvhtrace_engine::engine::{
    ArrayWrite, ArraysLayout, BackendFeatures, Batch, BatchOut, BatchTimes, DeviceApi, ScratchPlan,
};
use bvhtrace_engine::plan::DeviceLimits;
use bvhtrace_engine::upload::{ArrayRole, DeviceArray};
use bvhtrace_engine::walks::FULL_STACK_SIZE;
use bvhtrace_engine::{
    BvhStorage, DriverTuning, Engine, KernelKey, TraceError, Tracer, UploadOptions,
};
use glam::{Affine3A, Vec3};

/// A device that holds bytes. Its kernel answers ray `i` with `prim = origin.x` (so the
/// order of hits across submissions shows), or [`INCOMPLETE`] for rays with `origin.y`
/// above 0 (as a CPU driver's trip budget would).
struct Mock {
    limits: DeviceLimits,
    tuning: DriverTuning,
    /// `(role, bytes written, replaced)` of every update.
    writes: Mutex<Vec<(ArrayRole, usize, bool)>>,
    /// Rays per submission seen.
    batches: Mutex<Vec<usize>>,
    scratch: Mutex<Vec<ScratchPlan>>,
    /// Submissions (`'s'`) and read backs (`'f'`), with the scratch each used.
    order: Mutex<Vec<(char, usize)>>,
}

fn mock(tuning: DriverTuning) -> Mock {
    Mock {
        limits: DeviceLimits {
            max_storage_buffer_binding_size: 1 << 30,
            max_buffer_size: 1 << 30,
            max_compute_workgroups_per_dimension: 65_535,
            min_storage_buffer_offset_alignment: 256,
            max_texture_dimension_2d: 16_384,
            max_storage_buffers_per_shader_stage: 8,
        },
        tuning,
        writes: Mutex::new(Vec::new()),
        batches: Mutex::new(Vec::new()),
        scratch: Mutex::new(Vec::new()),
        order: Mutex::new(Vec::new()),
    }
}

type Arrays = Vec<(ArrayRole, Vec<u8>)>;

impl DeviceApi for Mock {
    type Arrays = Arrays;
    /// Which scratch, in the order they were made.
    type Scratch = usize;
    type Submitted = Vec<Hit>;

    fn name(&self) -> &'static str {
        "mock"
    }
    fn device_name(&self) -> String {
        "bytes".into()
    }
    fn limits(&self) -> &DeviceLimits {
        &self.limits
    }
    fn tuning(&self) -> &DriverTuning {
        &self.tuning
    }
    fn has_timestamps(&self) -> bool {
        true
    }
    fn features(&self) -> BackendFeatures {
        BackendFeatures {
            textures: true,
            vertex_attributes: true,
            f64: false,
        }
    }
    fn prepare_kernel(&self, key: KernelKey) -> Result<(), TraceError> {
        self.features().check(&key, || "bytes".into())
    }
    fn create_arrays(
        &self,
        _: ArraysLayout,
        arrays: &[DeviceArray<'_>],
    ) -> Result<Arrays, TraceError> {
        Ok(arrays.iter().map(|a| (a.role, a.bytes.to_vec())).collect())
    }
    fn write_arrays(
        &self,
        arrays: &mut Arrays,
        _: ArraysLayout,
        writes: &[ArrayWrite<'_>],
    ) -> Result<(), TraceError> {
        for w in writes {
            let a = &w.array;
            self.writes
                .lock()
                .unwrap()
                .push((a.role, a.bytes.len(), w.replace));
            let slot = arrays.iter_mut().find(|(r, _)| *r == a.role).unwrap();
            if w.replace {
                slot.1 = a.bytes.to_vec();
            } else {
                slot.1[..a.bytes.len()].copy_from_slice(&a.bytes);
            }
        }
        Ok(())
    }
    fn create_scratch(&self, plan: &ScratchPlan) -> Result<usize, TraceError> {
        let mut plans = self.scratch.lock().unwrap();
        plans.push(*plan);
        Ok(plans.len() - 1)
    }
    fn submit_batch(
        &self,
        _: &Arrays,
        scratch: &usize,
        batch: Batch<'_>,
    ) -> Result<Vec<Hit>, TraceError> {
        self.batches.lock().unwrap().push(batch.rays.len());
        self.order.lock().unwrap().push(('s', *scratch));
        Ok(batch
            .rays
            .iter()
            .map(|r| {
                let prim = if r.origin[1] > 0.0 {
                    INCOMPLETE
                } else {
                    r.origin[0] as u32
                };
                Hit {
                    prim,
                    ..Hit::miss(r.t_max)
                }
            })
            .collect())
    }
    async fn finish_batch<'a>(
        &'a self,
        scratch: &'a usize,
        hits: Vec<Hit>,
        out: BatchOut<'a>,
    ) -> Result<BatchTimes, TraceError> {
        self.order.lock().unwrap().push(('f', *scratch));
        out.hits.extend(hits);
        if let Some(c) = out.counters {
            c.resize(out.hits.len(), Default::default());
        }
        Ok(BatchTimes {
            gpu_ms: Some(0.5),
            phases: TracePhases {
                upload_ms: 0.25,
                device_ms: 1.0,
                readback_ms: 0.125,
            },
        })
    }
}

fn triangles(n: usize, scale: f32) -> Vec<Triangle> {
    (0..n)
        .map(|i| {
            let x = i as f32 * 2.0;
            [
                Vec3::new(x, 0.0, 0.0) * scale,
                Vec3::new(x + 1.0, 0.0, 0.0) * scale,
                Vec3::new(x, 1.0, 0.0) * scale,
            ]
        })
        .collect()
}

fn one_mesh() -> FlatBvh {
    FlatBvh::build(&triangles(40, 1.0), &BuildOptions::default()).expect("build")
}

fn two_levels() -> InstancedBvh {
    let instances = (0..4)
        .map(|k| Instance::new(k % 2, Affine3A::from_translation(Vec3::Z * k as f32)))
        .collect();
    InstancedBvh::build(
        &[triangles(30, 1.0), triangles(12, 0.5)],
        instances,
        &BuildOptions::default(),
    )
    .expect("two levels")
}

fn arrays_of(e: &Engine<Mock>) -> Arrays {
    let mut a = e.arrays().clone();
    a.sort_by_key(|(r, _)| format!("{r:?}"));
    a
}

/// Misuse gets one answer from the engine, whatever the backend: a tree too deep for the
/// full stack is refused at the upload when the full stack is listed and at trace time
/// otherwise; the wide walk on an upload without the wide layout names both fixes; a walk
/// whose arrays were left out says which.
#[test]
fn misuse_gets_the_same_error_at_the_same_point() {
    let mut deep = one_mesh();
    *deep.parts_mut().depth = FULL_STACK_SIZE + 1;
    let gpu = mock(DriverTuning::GPU);
    assert!(matches!(
        Engine::upload(gpu, &deep, &UploadOptions::all()),
        Err(TraceError::TooDeep { .. })
    ));
    let fitting = UploadOptions::fitting(&deep);
    assert!(!fitting.traversals.contains(&Traversal::FullStack));
    let e = Engine::upload(mock(DriverTuning::GPU), &deep, &fitting).expect("upload");
    let rays = [Ray::new(Vec3::new(1.0, -1.0, 0.5), Vec3::Y)];
    let full = TraceOptions::closest(Traversal::FullStack);
    for err in [
        e.supports(&full).unwrap_err(),
        e.trace(&rays, &full).unwrap_err(),
    ] {
        assert!(matches!(err, TraceError::TooDeep { .. }), "{err}");
    }
    e.supports(&TraceOptions::closest(Traversal::Stackless))
        .expect("stackless takes any depth");

    let wide = TraceOptions::closest(Traversal::Wide);
    let err = e.trace(&rays, &wide).unwrap_err();
    let msg = err.to_string();
    assert!(matches!(err, TraceError::WideLayoutMissing { .. }), "{msg}");
    assert!(
        msg.contains("UploadOptions::traversals") && msg.contains("build_wide"),
        "{msg}"
    );
    assert!(e.kernels_used().is_empty(), "a refused trace ran no kernel");

    // Wide only: the binary walks are refused; the tree had no wide layout, so it was
    // collapsed for the upload (the wide layout is built on demand).
    let bvh = one_mesh();
    assert!(bvh.wide().is_none());
    let e = Engine::upload(
        mock(DriverTuning::GPU),
        &bvh,
        &UploadOptions::for_traversal(Traversal::Wide),
    )
    .expect("wide only");
    assert!(e.tree().wide && !e.tree().binary);
    assert!(e.arrays().iter().all(|(r, _)| r.is_wide()));
    assert!(matches!(
        e.supports(&full),
        Err(TraceError::TraversalNotUploaded { .. })
    ));
    let e = Engine::upload(
        mock(DriverTuning::GPU),
        &bvh,
        &UploadOptions::for_traversal(Traversal::FullStack),
    )
    .expect("full stack only");
    assert!(matches!(
        e.supports(&TraceOptions::closest(Traversal::Stackless)),
        Err(TraceError::EscapesNotUploaded { .. })
    ));
    let f64 = full.with_precision(bvhtrace_core::Precision::WatertightF64);
    assert!(matches!(
        e.supports(&f64),
        Err(TraceError::PrecisionUnsupported { .. })
    ));
}

/// `Tracer::update` writes the top level and the instances only when the meshes did not
/// change, everything when they did; either way the device holds the bytes a fresh
/// upload of the new tree would.
#[test]
fn update_writes_what_changed_and_matches_a_fresh_upload() {
    let mut ib = two_levels();
    let opts = UploadOptions::all().with_traversal(Traversal::Wide);
    let mut e = Engine::upload(mock(DriverTuning::GPU), ib.bvh(), &opts).expect("upload");
    let moved: Vec<Affine3A> = ib
        .instances()
        .iter()
        .map(|i| Affine3A::from_rotation_y(0.3) * i.transform)
        .collect();
    ib.set_transforms(&moved).expect("move");
    Tracer::update(&mut e, ib.bvh()).expect("top-level update");
    let writes = std::mem::take(&mut *e.device().writes.lock().unwrap());
    let written = |role| writes.iter().find(|w| w.0 == role).map(|w| w.1);
    let top = ib.bvh().top_nodes() as usize;
    assert_eq!(written(ArrayRole::Nodes), Some(top * 32), "{writes:?}");
    assert_eq!(written(ArrayRole::Triangles), None, "{writes:?}");
    assert!(written(ArrayRole::Instances).is_some());
    assert!(
        written(ArrayRole::WideNodes).is_some(),
        "the wide layout follows"
    );
    let fresh = Engine::upload(mock(DriverTuning::GPU), ib.bvh(), &opts).expect("fresh");
    assert_eq!(arrays_of(&e), arrays_of(&fresh));

    let bent: Vec<Triangle> = triangles(12, 0.7);
    ib.refit_mesh(1, &bent).expect("refit");
    Tracer::update(&mut e, ib.bvh()).expect("update after a refit");
    let writes = std::mem::take(&mut *e.device().writes.lock().unwrap());
    let written = |role| writes.iter().find(|w| w.0 == role).map(|w| w.1);
    assert_eq!(written(ArrayRole::Nodes), Some(ib.bvh().nodes().len() * 32));
    assert!(written(ArrayRole::Triangles).is_some(), "{writes:?}");
    let fresh = Engine::upload(mock(DriverTuning::GPU), ib.bvh(), &opts).expect("fresh");
    assert_eq!(arrays_of(&e), arrays_of(&fresh));
    assert_eq!(e.stats().total_bytes(), fresh.stats().total_bytes());

    // Another shape is a new upload.
    assert!(matches!(
        Tracer::update(&mut e, &one_mesh()),
        Err(TraceError::BadBuffer { .. })
    ));
}

/// The driver splits a batch into submissions the device's buffers hold, keeps the hits
/// in order, grows its scratch only when needed (counters once asked for, kept), sums the
/// GPU times, finishes incomplete rays on the host copy of a CPU driver, and lists each
/// kernel it ran once.
#[test]
fn the_driver_splits_orders_finishes_and_counts_kernels() {
    let mut dev = mock(DriverTuning::cpu_driver(4));
    // Room for 4096 rays of 32 bytes per buffer, in dispatches of 256.
    dev.limits.max_buffer_size = 4096 * 32;
    dev.limits.max_storage_buffer_binding_size = 256 * 32;
    let bvh = one_mesh();
    let buffers = UploadOptions::all().with_storage(BvhStorage::Buffers);
    let e = Engine::upload(dev, &bvh, &buffers).expect("upload");
    let n = 10_000;
    let mut rays: Vec<Ray> = (0..n)
        .map(|i| Ray::new(Vec3::new(i as f32, -1.0, 0.5), Vec3::Y))
        .collect();
    // Two rays the "kernel" gives up on: finished by the CPU walk.
    for i in [17, 9_999] {
        rays[i] = Ray::new(Vec3::new(2.0 * 7.0 + 0.25, 0.25, -1.0), Vec3::Z);
    }
    let opts = TraceOptions::closest(Traversal::Stackless);
    let out = e.trace(&rays, &opts).expect("trace");
    assert_eq!(*e.device().batches.lock().unwrap(), vec![4096, 4096, 1808]);
    assert_eq!(out.gpu_ms, Some(1.5));
    // Each submission's phases, summed; the upload also holds the pass over the rays.
    let phases = out.phases.expect("a device trace's phases");
    assert_eq!((phases.device_ms, phases.readback_ms), (3.0, 0.375));
    assert!(phases.upload_ms >= 0.75, "{phases:?}");
    assert_eq!(out.incomplete, 2);
    let cpu = trace_rays(&bvh, &rays, &opts).hits;
    for (i, h) in out.hits.iter().enumerate() {
        match i {
            17 | 9_999 => assert_eq!(*h, cpu[i], "ray {i}"),
            _ => assert_eq!(h.prim, i as u32, "ray {i}"),
        }
    }
    assert!(cpu[17].is_hit());

    let counted = opts.with_counters(true);
    e.trace(&rays[..10], &counted).expect("counters");
    e.trace(&rays[..10], &opts).expect("again");
    let plans = e.device().scratch.lock().unwrap().clone();
    assert_eq!(plans.len(), 2, "{plans:?}");
    assert!(!plans[0].counters && plans[1].counters && plans[1].capacity == 4096);
    let any = TraceOptions::new(Traversal::Stackless, bvhtrace_core::Query::Any);
    e.trace(&rays[..1], &any).expect("any");
    let used = e.kernels_used();
    assert_eq!(used.len(), 3, "{used:?}");
    assert!(used[1].counters && used[2].query != used[0].query);
    assert_eq!(used[0].storage, BvhStorage::Buffers);

    // The CPU driver's own storage, textures: the rays go in a texture, one dispatch per
    // submission.
    let mut dev = mock(DriverTuning::cpu_driver(4));
    dev.limits.max_storage_buffer_binding_size = 256 * 32;
    let e = Engine::upload(dev, &bvh, &UploadOptions::all()).expect("upload");
    assert_eq!(e.tree().storage, BvhStorage::Textures);
    e.trace(&rays[..600], &opts).expect("trace");
    assert_eq!(*e.device().batches.lock().unwrap(), vec![256, 256, 88]);
    assert_eq!(
        e.kernels_used()[0].rays,
        bvhtrace_engine::storage::RayInput::Texture
    );
}

/// With two submissions in flight (a GPU's tuning), a trace is split into submissions of
/// `submission_rays` on two scratches in turn, each read back before its scratch takes the
/// next one, the hits in order; a second trace reuses both scratches.
#[test]
fn two_submissions_in_flight_alternate_scratch_and_keep_the_order() {
    let tuning = DriverTuning {
        submission_rays: 256,
        ..DriverTuning::GPU
    };
    assert_eq!(tuning.in_flight, 2);
    let e = Engine::upload(mock(tuning), &one_mesh(), &UploadOptions::all()).expect("upload");
    let rays: Vec<Ray> = (0..1000)
        .map(|i| Ray::new(Vec3::new(i as f32, -1.0, 0.5), Vec3::Y))
        .collect();
    let opts = TraceOptions::closest(Traversal::FullStack);
    let out = e.trace(&rays, &opts).expect("trace");
    assert!(out.hits.iter().enumerate().all(|(i, h)| h.prim == i as u32));
    assert_eq!(out.gpu_ms, Some(2.0));
    assert_eq!(
        *e.device().batches.lock().unwrap(),
        vec![256, 256, 256, 232]
    );
    let order = e.device().order.lock().unwrap().clone();
    let want = [
        ('s', 0),
        ('s', 1),
        ('f', 0),
        ('s', 0),
        ('f', 1),
        ('s', 1),
        ('f', 0),
        ('f', 1),
    ];
    assert_eq!(order, want);
    let plans = e.device().scratch.lock().unwrap().clone();
    assert_eq!(plans.len(), 2, "{plans:?}");
    assert!(plans.iter().all(|p| p.capacity == 256));
    e.trace(&rays[..300], &opts).expect("again");
    assert_eq!(e.device().scratch.lock().unwrap().len(), 2, "reused");
    // A trace of one submission needs one scratch: the kept ones serve.
    e.trace(&rays[..10], &opts).expect("one");
    assert_eq!(e.device().order.lock().unwrap().len(), 8 + 4 + 2);
    assert_eq!(e.device().scratch.lock().unwrap().len(), 2);
}
