//! The conformance suite's tracer factory: every way to trace, opened once per test, so
//! each parity test runs on each tracer. A new backend is one more line in [`tracers`].
#![allow(dead_code)]

use bvhtrace_core::FlatBvh;
use bvhtrace_core::Traversal;
use bvhtrace_gpu::{
    BvhStorage, ContextOptions, CpuTracer, GpuBvh, GpuContext, TraceError, Tracer, UploadOptions,
};
use bvhtrace_vk::{AdapterChoice, DriverTuning, VkBvh, VkContext, VkOptions};

/// Storage textures the wgpu texture storage binds in one stage.
const STORAGE_TEXTURES_USED: u32 = 5;

/// The devices the device tracers run on; a backend without a device is left out (SKIP
/// printed), so the suite still checks the others.
pub struct Devices {
    /// wgpu's context.
    pub wgpu: Option<GpuContext>,
    /// ash's context, with the validation layer on when it is installed: every test
    /// checks it reported no error ([`Devices::check_validation`]).
    pub vk: Option<VkContext>,
}

impl Devices {
    /// Both backends on their own choice of device, with the device's tuning: opened
    /// once per test binary and shared by its tests, so that each kernel is compiled once.
    pub fn open(test: &str) -> &'static Devices {
        static SHARED: std::sync::OnceLock<Devices> = std::sync::OnceLock::new();
        SHARED.get_or_init(|| Devices::with_tuning(test, None))
    }

    /// [`Devices::open`] with both backends on `tuning` (`None`: the device's own; wgpu
    /// keeps buffers as its default storage where the device has too few storage-texture
    /// bindings).
    pub fn with_tuning(test: &str, tuning: Option<DriverTuning>) -> Devices {
        let wgpu =
            skip_without_device(test, "wgpu", GpuContext::new(AdapterChoice::Auto)).map(|ctx| {
                match tuning {
                    Some(t) => retune_wgpu(&ctx, t),
                    None => ctx,
                }
            });
        let vk = skip_without_device(test, "ash", open_vk(tuning));
        Devices { wgpu, vk }
    }

    /// These devices again, each with its tuning changed by `f` (the others' contexts
    /// are dropped with `self`).
    pub fn retuned(&self, f: impl Fn(DriverTuning) -> DriverTuning) -> Devices {
        Devices {
            wgpu: self.wgpu.as_ref().map(|c| retune_wgpu(c, f(*c.tuning()))),
            vk: self
                .vk
                .as_ref()
                .map(|c| open_vk(Some(f(*c.tuning()))).expect("ash, retuned")),
        }
    }

    /// True when some device tracer opened.
    pub fn any(&self) -> bool {
        self.wgpu.is_some() || self.vk.is_some()
    }

    /// ash's validation layer reported no error (on shared devices: in any test so far).
    pub fn check_validation(&self) {
        if let Some(vk) = &self.vk {
            assert_eq!(vk.validation_errors(), 0, "Vulkan validation errors");
        }
    }
}

/// ash on `tuning`, with validation.
fn open_vk(tuning: Option<DriverTuning>) -> Result<VkContext, TraceError> {
    VkContext::with_options(&VkOptions {
        adapter: AdapterChoice::Auto,
        validation: true,
        tuning,
    })
}

/// True when the wgpu device binds enough storage textures for the texture storage.
pub fn wgpu_has_textures(ctx: &GpuContext) -> bool {
    ctx.device().limits().max_storage_textures_per_shader_stage >= STORAGE_TEXTURES_USED
}

/// `ctx`'s device with `tuning` (its storage buffers where textures do not fit).
fn retune_wgpu(ctx: &GpuContext, mut tuning: DriverTuning) -> GpuContext {
    if !wgpu_has_textures(ctx) {
        tuning.storage = BvhStorage::Buffers;
    }
    let retuned = GpuContext::from_device_with(
        ctx.device().clone(),
        ctx.queue().clone(),
        ctx.adapter_info().clone(),
        &ContextOptions {
            tuning: Some(tuning),
            ..ContextOptions::default()
        },
    )
    .expect("wgpu, retuned");
    assert_eq!(*retuned.tuning(), tuning);
    retuned
}

/// The context, or `None` after SKIP when the machine has no such device.
fn skip_without_device<C>(test: &str, backend: &str, ctx: Result<C, TraceError>) -> Option<C> {
    match ctx {
        Ok(c) => Some(c),
        Err(e @ TraceError::NoAdapter { .. }) => {
            eprintln!("SKIP {test} on {backend}: {e}");
            None
        }
        Err(e) => panic!("{test}: cannot open {backend}: {e}"),
    }
}

/// Every tracer over `bvh`: the CPU twin; wgpu with the BVH in buffers, and in textures
/// where the device binds them (every walk uploaded, the wide layout too, in the same
/// storage); and ash (which uploads the wide layout when `bvh` has one: build it first
/// for the wide walk). A tracer whose upload refuses `bvh` is an error here.
pub fn tracers<'a>(devices: &Devices, bvh: &'a FlatBvh) -> Vec<Box<dyn Tracer + 'a>> {
    let mut out: Vec<Box<dyn Tracer + 'a>> = vec![Box::new(CpuTracer::new(bvh))];
    if let Some(ctx) = &devices.wgpu {
        let walks = if bvh.depth() > bvhtrace_gpu::engine::walks::FULL_STACK_SIZE {
            UploadOptions::for_traversal(Traversal::Stackless)
        } else {
            UploadOptions::all()
        };
        let mut storages = vec![BvhStorage::Buffers];
        if wgpu_has_textures(ctx) {
            storages.push(BvhStorage::Textures);
        } else {
            eprintln!("SKIP wgpu textures: too few storage-texture bindings");
        }
        for storage in storages {
            let opts = walks
                .clone()
                .with_storage(storage)
                .with_traversal(Traversal::Wide);
            let gpu = GpuBvh::upload(ctx, bvh, &opts).expect("wgpu upload");
            let textures = storage == BvhStorage::Textures;
            assert_eq!(
                (gpu.wide_buffers().is_some(), gpu.wide_textures().is_some()),
                (!textures, textures),
                "the wide layout is not in {storage:?}"
            );
            out.push(Box::new(gpu));
        }
    }
    if let Some(ctx) = &devices.vk {
        let fitting = UploadOptions::fitting(bvh);
        out.push(Box::new(
            VkBvh::upload(ctx, bvh, &fitting).expect("ash upload"),
        ));
    }
    out
}

/// A tracer's name in failures: its backend, and where a device keeps the tree.
pub fn name(t: &dyn Tracer) -> String {
    match t.upload_stats() {
        Some(s) => format!("{} ({:?})", t.backend(), s.storage),
        None => t.backend().to_string(),
    }
}
