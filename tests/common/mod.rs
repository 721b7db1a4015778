//! The conformance suite's tracer factory: every way to trace, opened once per test, so
//! each parity test runs on each tracer. A new backend is one more line in [`tracers`].
#![allow(dead_code)]

use bvhtrace_core::FlatBvh;
use bvhtrace_core::Traversal;
use bvhtrace_gpu::{BvhStorage, CpuTracer, GpuBvh, GpuContext, TraceError, Tracer, UploadOptions};
use bvhtrace_vk::{AdapterChoice, DriverTuning, VkBvh, VkContext, VkOptions};

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
    /// Both backends on their own choice of device, with the device's tuning.
    pub fn open(test: &str) -> Devices {
        Devices::with_tuning(test, None)
    }

    /// [`Devices::open`] with ash on `tuning` (`None`: the device's own).
    pub fn with_tuning(test: &str, tuning: Option<DriverTuning>) -> Devices {
        let wgpu = skip_without_device(test, "wgpu", GpuContext::new(AdapterChoice::Auto));
        let vk = skip_without_device(
            test,
            "ash",
            VkContext::with_options(&VkOptions {
                adapter: AdapterChoice::Auto,
                validation: true,
                tuning,
            }),
        );
        Devices { wgpu, vk }
    }

    /// True when some device tracer opened.
    pub fn any(&self) -> bool {
        self.wgpu.is_some() || self.vk.is_some()
    }

    /// ash's validation layer reported no error.
    pub fn check_validation(&self) {
        if let Some(vk) = &self.vk {
            assert_eq!(vk.validation_errors(), 0, "Vulkan validation errors");
        }
    }
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

/// Every tracer over `bvh`: the CPU twin, wgpu (the BVH in buffers, every walk uploaded,
/// the wide layout too) and ash (which uploads the wide layout when `bvh` has one: build
/// it first for the wide walk). A tracer whose upload refuses `bvh` is an error here.
pub fn tracers<'a>(devices: &Devices, bvh: &'a FlatBvh) -> Vec<Box<dyn Tracer + 'a>> {
    let mut out: Vec<Box<dyn Tracer + 'a>> = vec![Box::new(CpuTracer::new(bvh))];
    if let Some(ctx) = &devices.wgpu {
        let opts = UploadOptions::all()
            .with_storage(BvhStorage::Buffers)
            .with_traversal(Traversal::Wide);
        let opts = if bvh.depth() > bvhtrace_gpu::kernels::FULL_STACK_SIZE {
            UploadOptions::for_traversal(Traversal::Stackless)
                .with_storage(BvhStorage::Buffers)
                .with_traversal(Traversal::Wide)
        } else {
            opts
        };
        out.push(Box::new(
            GpuBvh::upload(ctx, bvh, &opts).expect("wgpu upload"),
        ));
    }
    if let Some(ctx) = &devices.vk {
        out.push(Box::new(VkBvh::upload(ctx, bvh).expect("ash upload")));
    }
    out
}
