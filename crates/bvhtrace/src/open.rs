//! Opening a tracer: the backend, then a storage, layout and walk that fit the device.

use std::borrow::Borrow;
use std::fmt;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, HitFilter, TraceOptions, Traversal};
use bvhtrace_engine::tracer::SendSync;
use bvhtrace_engine::{AdapterChoice, BvhStorage, CpuTracer, DriverTuning, TraceError, Tracer};
use bvhtrace_gpu::{ContextOptions, GpuBvh, GpuContext, UploadOptions};
#[cfg(not(target_arch = "wasm32"))]
use bvhtrace_vk::{VkBvh, VkContext, VkOptions};

use crate::Backend;
use crate::cpu::FastCpuTracer;

/// What [`open`] opens, and for what.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct OpenOptions {
    /// The backend; [`Backend::Auto`] picks.
    pub backend: Backend,
    /// The adapter of a device backend. The library reads no environment variable: a front
    /// end that honours [`bvhtrace_engine::device::ADAPTER_ENV`] passes it on as
    /// [`AdapterChoice::Named`].
    pub adapter: AdapterChoice,
    /// The walks the caller will trace with, the first its default. Empty: the backend's
    /// fastest walk ([`Traversal::GPU_DEFAULT`] on a device, [`Traversal::CPU_DEFAULT`] on
    /// the CPU), settled before the upload so that only what it reads is uploaded, and
    /// another walk (the full stack, the wide layout) when it exceeds a device limit.
    pub traversals: Vec<Traversal>,
    /// Buffers or textures on wgpu; `None`: the device's choice
    /// ([`DriverTuning::storage`]), and the other one when that exceeds a limit. The
    /// Vulkan backend reads buffers only.
    pub storage: Option<BvhStorage>,
    /// The CPU-driver measures for the device; `None`: [`DriverTuning::for_device`].
    pub tuning: Option<DriverTuning>,
    /// Enable `VK_LAYER_KHRONOS_validation` on the Vulkan backend when it is installed (a
    /// front end honouring `bvhtrace_vk::VALIDATION_ENV` passes it on here).
    pub validation: bool,
    /// A filter every candidate hit passes through, your own rule as a closure. The CPU
    /// walks apply it; the device backends cannot run Rust, so [`Backend::Auto`] then
    /// traces on the CPU (and says why), and a device backend asked for by name refuses.
    /// Alpha-tested materials need no filter: their masks travel with the BVH
    /// (`FlatBvh::set_masks`, attached by `bvhtrace_scene::Scene::tracing_bvh`) and every
    /// backend cuts them; on a device write your rule in WGSL
    /// (`LibraryShape::with_filter`).
    pub filter: Option<SharedFilter>,
}

/// A [`HitFilter`] shared by the tracers that apply it ([`OpenOptions::filter`]).
#[derive(Clone)]
pub struct SharedFilter(pub Arc<dyn HitFilter + Send>);

impl std::fmt::Debug for SharedFilter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SharedFilter")
    }
}

impl PartialEq for SharedFilter {
    /// The same filter object.
    fn eq(&self, other: &SharedFilter) -> bool {
        Arc::ptr_eq(&self.0, &other.0)
    }
}

impl OpenOptions {
    /// The defaults on `backend`.
    pub fn new(backend: Backend) -> OpenOptions {
        OpenOptions {
            backend,
            ..OpenOptions::default()
        }
    }

    /// The same options on this adapter.
    pub fn with_adapter(mut self, adapter: AdapterChoice) -> OpenOptions {
        self.adapter = adapter;
        self
    }

    /// The same options with `traversal` listed too (the first listed is the default).
    pub fn with_traversal(mut self, traversal: Traversal) -> OpenOptions {
        if !self.traversals.contains(&traversal) {
            self.traversals.push(traversal);
        }
        self
    }

    /// The same options in this storage.
    pub fn with_storage(mut self, storage: BvhStorage) -> OpenOptions {
        self.storage = Some(storage);
        self
    }
}

/// A tracer [`open`] opened, and what was chosen and why.
pub struct Opened<'a> {
    /// The tracer.
    pub tracer: Box<dyn Tracer + 'a>,
    /// The backend it runs on (never [`Backend::Auto`]).
    pub backend: Backend,
    /// The device: the adapter's name and type, or the CPU's thread count.
    pub device: String,
    /// Where the tree was put on the device; `None` on the CPU.
    pub storage: Option<BvhStorage>,
    /// The walk to trace with when none is asked for: the first of
    /// [`OpenOptions::traversals`], else the one the backend and device settled on.
    pub traversal: Traversal,
    /// What was not as asked or as preferred, and why, as a sentence a front end prints
    /// (`None` when everything was).
    pub fallback: Option<String>,
    /// Why [`Backend::Auto`] chose ray queries or our walks on a device that offers ray
    /// queries, as a sentence ([`Device::choice`]); `None` otherwise.
    pub choice: Option<String>,
}

impl Opened<'_> {
    /// One line: backend, device, storage and walk.
    pub fn summary(&self) -> String {
        if self.backend == Backend::RayQuery {
            return format!("{} on {}, the driver's walk", self.backend, self.device);
        }
        let storage = self
            .storage
            .map_or(String::new(), |s| format!(", {} storage", storage_name(s)));
        format!(
            "{} on {}{storage}, {} walk",
            self.backend, self.device, self.traversal
        )
    }
}

impl fmt::Debug for Opened<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Opened")
            .field("backend", &self.backend)
            .field("device", &self.device)
            .field("storage", &self.storage)
            .field("traversal", &self.traversal)
            .field("fallback", &self.fallback)
            .field("choice", &self.choice)
            .finish_non_exhaustive()
    }
}

fn storage_name(s: BvhStorage) -> &'static str {
    match s {
        BvhStorage::Buffers => "buffer",
        BvhStorage::Textures => "texture",
    }
}

/// Opens the tracer `opts` asks for on `bvh` (borrowed, `Arc`-shared or owned: the CPU
/// walks trace it in place; a device backend uploads it and keeps no borrow).
///
/// [`Backend::Auto`] opens wgpu on the best Vulkan adapter, and the CPU walks when there
/// is none, or when the scene exceeds the device's limits every way; a named backend that
/// cannot open is an error. On a device, the walk is settled before the upload (the first
/// of [`OpenOptions::traversals`], else the backend's default), and when the tree exceeds
/// a device limit in the preferred storage, the other storage is tried, then (when no walk
/// was asked for) the full-stack walk, then the wide layout; when nothing fits, the error
/// is the preferred choice's, which names the limit ([`TraceError::TooLarge`],
/// [`TraceError::TooDeep`]). [`Opened::fallback`] says what was tried instead.
///
/// To open many trees on one device, open the [`Device`] once and call [`Device::open`].
pub fn open<'a, B>(bvh: B, opts: &OpenOptions) -> Result<Opened<'a>, TraceError>
where
    B: Borrow<FlatBvh> + Send + Sync + 'a,
{
    Device::new(opts)?.open(bvh, opts)
}

/// A backend opened once (the device and its pipeline cache), to open tracers on for many
/// trees. Cheap to clone: the device is shared.
#[derive(Clone)]
pub struct Device {
    inner: Inner,
    /// Opened as [`Backend::Auto`]: a tree over the device's limits goes to the CPU.
    auto: bool,
    /// Why this is not the backend asked for.
    fallback: Option<String>,
    /// Why [`Backend::Auto`] chose what it did on a device with ray queries.
    choice: Option<String>,
}

#[derive(Clone)]
enum Inner {
    Cpu,
    Wgpu(GpuContext),
    #[cfg(not(target_arch = "wasm32"))]
    Vulkan(VkContext),
    /// A wgpu device with ray queries, tracing with them.
    #[cfg(not(target_arch = "wasm32"))]
    RayQuery(GpuContext),
}

impl fmt::Debug for Device {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("Device")
            .field("backend", &self.backend())
            .field("name", &self.name())
            .field("fallback", &self.fallback)
            .finish()
    }
}

impl Device {
    /// Opens the backend and adapter `opts` asks for ([`Backend::Auto`]: wgpu on the best
    /// Vulkan adapter, with its ray queries where it has them in hardware, else the CPU,
    /// saying why in [`Device::fallback`] and [`Device::choice`]).
    pub fn new(opts: &OpenOptions) -> Result<Device, TraceError> {
        let mut choice = None;
        let inner = match opts.backend {
            Backend::Cpu => Inner::Cpu,
            Backend::Wgpu => Inner::Wgpu(wgpu_context(opts, false)?),
            #[cfg(not(target_arch = "wasm32"))]
            Backend::Vulkan => Inner::Vulkan(vulkan_context(opts)?),
            #[cfg(not(target_arch = "wasm32"))]
            Backend::RayQuery => {
                let ctx = wgpu_context(opts, true)?;
                if !ctx.has_ray_queries() {
                    return Err(TraceError::MissingFeature {
                        feature: "EXPERIMENTAL_RAY_QUERY",
                        needed_for: "the ray-query backend (Mesa 25's lavapipe has it; see \
                                     the README)",
                        adapter: ctx.adapter_info().name.clone(),
                    });
                }
                Inner::RayQuery(ctx)
            }
            #[cfg(target_arch = "wasm32")]
            Backend::Vulkan | Backend::RayQuery => {
                return Err(TraceError::NoAdapter {
                    details: format!(
                        ": the {} backend does not run in a browser (WebGPU has no ray \
                         queries, and ash no browser; use wgpu)",
                        opts.backend
                    ),
                });
            }
            Backend::Auto => match wgpu_context(opts, true) {
                Ok(ctx) => {
                    let (inner, why) = auto_choice(ctx);
                    choice = why;
                    inner
                }
                Err(e @ TraceError::NoAdapter { .. }) => {
                    return Ok(Device {
                        inner: Inner::Cpu,
                        auto: true,
                        fallback: Some(format!(
                            "there is no Vulkan adapter ({e}); tracing on the CPU"
                        )),
                        choice: None,
                    });
                }
                Err(e) => return Err(e),
            },
        };
        Ok(Device {
            inner,
            auto: opts.backend == Backend::Auto,
            fallback: None,
            choice,
        })
    }

    /// Why [`Backend::Auto`] chose ray queries or our walks, on a device that offers ray
    /// queries: hardware ray tracing is the faster path, a CPU driver's software ray
    /// queries are not (`None` on a device without them, and for a named backend).
    pub fn choice(&self) -> Option<&str> {
        self.choice.as_deref()
    }

    /// The CPU walks.
    pub fn cpu() -> Device {
        Device {
            inner: Inner::Cpu,
            auto: false,
            fallback: None,
            choice: None,
        }
    }

    /// A wgpu device the caller opened (an application's, eframe's).
    pub fn wgpu(ctx: GpuContext) -> Device {
        Device {
            inner: Inner::Wgpu(ctx),
            auto: false,
            fallback: None,
            choice: None,
        }
    }

    /// A Vulkan context the caller opened (not on wasm32).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn vulkan(ctx: VkContext) -> Device {
        Device {
            inner: Inner::Vulkan(ctx),
            auto: false,
            fallback: None,
            choice: None,
        }
    }

    /// A wgpu device the caller opened with ray queries
    /// ([`GpuContext::has_ray_queries`]), tracing with them (not on wasm32).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn ray_query(ctx: GpuContext) -> Result<Device, TraceError> {
        if !ctx.has_ray_queries() {
            return Err(TraceError::MissingFeature {
                feature: "EXPERIMENTAL_RAY_QUERY",
                needed_for: "the ray-query backend",
                adapter: ctx.adapter_info().name.clone(),
            });
        }
        Ok(Device {
            inner: Inner::RayQuery(ctx),
            auto: false,
            fallback: None,
            choice: None,
        })
    }

    /// The backend (never [`Backend::Auto`]).
    pub fn backend(&self) -> Backend {
        match self.inner {
            Inner::Cpu => Backend::Cpu,
            Inner::Wgpu(_) => Backend::Wgpu,
            #[cfg(not(target_arch = "wasm32"))]
            Inner::Vulkan(_) => Backend::Vulkan,
            #[cfg(not(target_arch = "wasm32"))]
            Inner::RayQuery(_) => Backend::RayQuery,
        }
    }

    /// The adapter's name and type, or `cpu`.
    pub fn name(&self) -> String {
        match &self.inner {
            Inner::Cpu => "cpu".to_string(),
            #[cfg(not(target_arch = "wasm32"))]
            Inner::RayQuery(c) => {
                let i = c.adapter_info();
                format!("{} ({:?})", i.name, i.device_type)
            }
            Inner::Wgpu(c) => {
                let i = c.adapter_info();
                format!("{} ({:?})", i.name, i.device_type)
            }
            #[cfg(not(target_arch = "wasm32"))]
            Inner::Vulkan(c) => {
                let i = c.device_info();
                format!("{} ({:?})", i.name, i.kind)
            }
        }
    }

    /// Why this is not the backend asked for (`None` when it is).
    pub fn fallback(&self) -> Option<&str> {
        self.fallback.as_deref()
    }

    /// The wgpu context, on wgpu (our walks or its ray queries).
    pub fn wgpu_context(&self) -> Option<&GpuContext> {
        match &self.inner {
            Inner::Wgpu(c) => Some(c),
            #[cfg(not(target_arch = "wasm32"))]
            Inner::RayQuery(c) => Some(c),
            _ => None,
        }
    }

    /// The Vulkan context, on Vulkan (not on wasm32).
    #[cfg(not(target_arch = "wasm32"))]
    pub fn vulkan_context(&self) -> Option<&VkContext> {
        match &self.inner {
            Inner::Vulkan(c) => Some(c),
            _ => None,
        }
    }

    /// The CPU-driver measures in force on a device backend (`None` on the CPU).
    pub fn tuning(&self) -> Option<DriverTuning> {
        match &self.inner {
            Inner::Cpu => None,
            Inner::Wgpu(c) => Some(*c.tuning()),
            #[cfg(not(target_arch = "wasm32"))]
            Inner::Vulkan(c) => Some(*c.tuning()),
            #[cfg(not(target_arch = "wasm32"))]
            Inner::RayQuery(c) => Some(*c.tuning()),
        }
    }

    /// [`Device::open`] for a tracer that keeps no borrow of `bvh` (a device upload, or
    /// the CPU walks on a shared copy): what a tracer factory hands out.
    pub fn open_owned(
        &self,
        bvh: &FlatBvh,
        opts: &OpenOptions,
    ) -> Result<Opened<'static>, TraceError> {
        let opened = match &self.inner {
            Inner::Cpu => return open_cpu(Arc::new(bvh.clone()), opts, self.fallback.clone()),
            Inner::Wgpu(ctx) => open_on_wgpu(ctx, bvh, opts),
            #[cfg(not(target_arch = "wasm32"))]
            Inner::Vulkan(ctx) => open_on_vulkan(ctx, bvh, opts),
            #[cfg(not(target_arch = "wasm32"))]
            Inner::RayQuery(ctx) => self.ray_query_or_walks(ctx, bvh, opts),
        };
        match opened {
            Err(e) if self.auto && exceeds_a_limit(&e) => {
                let why = format!(
                    "the scene does not fit {} ({e}); tracing on the CPU",
                    self.name()
                );
                open_cpu(Arc::new(bvh.clone()), opts, Some(why))
            }
            other => other.map(|o| self.with_choice(o)),
        }
    }

    /// [`Opened::choice`] from the device's.
    fn with_choice<'a>(&self, mut opened: Opened<'a>) -> Opened<'a> {
        opened.choice = self.choice.clone();
        opened
    }

    /// Ray queries on `ctx`; for [`Backend::Auto`], our walks on the same device when
    /// the tree exceeds a limit of the ray-query upload.
    #[cfg(not(target_arch = "wasm32"))]
    fn ray_query_or_walks(
        &self,
        ctx: &GpuContext,
        bvh: &FlatBvh,
        opts: &OpenOptions,
    ) -> Result<Opened<'static>, TraceError> {
        match open_on_ray_query(ctx, bvh, opts) {
            Err(e) if self.auto && exceeds_a_limit(&e) => {
                let mut o = open_on_wgpu(ctx, bvh, opts)?;
                o.fallback = Some(format!(
                    "the scene does not fit the ray-query upload ({e}); tracing with our walks"
                ));
                Ok(o)
            }
            other => other,
        }
    }

    /// A tracer factory on this device: each call opens a tracer for the tree, uploaded
    /// for the walks listed ([`Device::open_owned`]). For a test suite or a stress run that
    /// takes tracers from its caller.
    pub fn tracer_factory(
        &self,
    ) -> impl Fn(&FlatBvh, &[Traversal]) -> Result<Box<dyn Tracer>, TraceError> + SendSync + 'static
    {
        let device = self.clone();
        move |bvh, walks| {
            let opts = OpenOptions {
                traversals: walks.to_vec(),
                ..OpenOptions::default()
            };
            Ok(device.open_owned(bvh, &opts)?.tracer)
        }
    }

    /// Opens a tracer for `bvh` on this device, as [`open`] does (`opts.backend`,
    /// `opts.adapter` and `opts.tuning` were the device's business and are not read).
    pub fn open<'a, B>(&self, bvh: B, opts: &OpenOptions) -> Result<Opened<'a>, TraceError>
    where
        B: Borrow<FlatBvh> + Send + Sync + 'a,
    {
        if opts.filter.is_some() && !matches!(self.inner, Inner::Cpu) {
            if !self.auto {
                let backend = match self.inner {
                    Inner::Cpu => "cpu",
                    Inner::Wgpu(_) => "wgpu",
                    #[cfg(not(target_arch = "wasm32"))]
                    Inner::Vulkan(_) => "vulkan",
                    #[cfg(not(target_arch = "wasm32"))]
                    Inner::RayQuery(_) => "ray-query",
                };
                return Err(TraceError::Unsupported {
                    backend,
                    what: "hit filters written in Rust: the CPU backend applies them (alpha \
                           masks travel with the BVH instead, FlatBvh::set_masks)"
                        .into(),
                });
            }
            let why = "only the CPU walks apply a hit filter written in Rust: tracing on the CPU";
            return open_cpu(bvh, opts, Some(why.into()));
        }
        let opened = match &self.inner {
            Inner::Cpu => return open_cpu(bvh, opts, self.fallback.clone()),
            Inner::Wgpu(ctx) => open_on_wgpu(ctx, bvh.borrow(), opts),
            #[cfg(not(target_arch = "wasm32"))]
            Inner::Vulkan(ctx) => open_on_vulkan(ctx, bvh.borrow(), opts),
            #[cfg(not(target_arch = "wasm32"))]
            Inner::RayQuery(ctx) => self.ray_query_or_walks(ctx, bvh.borrow(), opts),
        };
        match opened {
            Err(e) if self.auto && exceeds_a_limit(&e) => {
                let why = format!(
                    "the scene does not fit {} ({e}); tracing on the CPU",
                    self.name()
                );
                open_cpu(bvh, opts, Some(why))
            }
            other => other.map(|o| self.with_choice(o)),
        }
    }
}

/// The wgpu context `opts` asks for, with ray queries when `ray_queries` and the adapter
/// has them.
fn wgpu_context(opts: &OpenOptions, ray_queries: bool) -> Result<GpuContext, TraceError> {
    let options = ContextOptions {
        tuning: opts.tuning,
        ray_queries,
        ..ContextOptions::default()
    };
    GpuContext::new_with(opts.adapter.clone(), &options)
}

/// [`Backend::Auto`]'s choice on a wgpu device: its ray queries where they run on
/// ray-tracing hardware (any adapter but a CPU driver), our walks elsewhere; and why, when
/// the device offers ray queries.
fn auto_choice(ctx: GpuContext) -> (Inner, Option<String>) {
    if !ctx.has_ray_queries() {
        return (Inner::Wgpu(ctx), None);
    }
    let name = ctx.adapter_info().name.clone();
    if ctx.adapter_info().device_type == bvhtrace_gpu::wgpu::DeviceType::Cpu {
        let why = format!(
            "{name} offers ray queries, but it is a CPU driver, where they run in software and \
             our walks trace several times faster; tracing with our walks"
        );
        return (Inner::Wgpu(ctx), Some(why));
    }
    #[cfg(not(target_arch = "wasm32"))]
    {
        let why = format!("{name} has ray queries in hardware; tracing with them");
        (Inner::RayQuery(ctx), Some(why))
    }
    #[cfg(target_arch = "wasm32")]
    (Inner::Wgpu(ctx), None)
}

/// The Vulkan context `opts` asks for.
#[cfg(not(target_arch = "wasm32"))]
fn vulkan_context(opts: &OpenOptions) -> Result<VkContext, TraceError> {
    VkContext::with_options(&VkOptions {
        adapter: opts.adapter.clone(),
        validation: opts.validation,
        tuning: opts.tuning,
    })
}

/// True for the errors another storage, layout or walk may avoid.
fn exceeds_a_limit(e: &TraceError) -> bool {
    matches!(
        e,
        TraceError::TooLarge { .. }
            | TraceError::TooDeep { .. }
            | TraceError::LimitTooLow { .. }
            | TraceError::WideLayoutMissing { .. }
    )
}

/// One way to put the tree on a device: the walks it is uploaded for (the first the
/// default) and the storage.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Choice {
    pub(crate) walks: Vec<Traversal>,
    pub(crate) storage: BvhStorage,
}

impl fmt::Display for Choice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let walks: Vec<String> = self.walks.iter().map(ToString::to_string).collect();
        write!(
            f,
            "the {} walk in {} storage",
            walks.join("/"),
            storage_name(self.storage)
        )
    }
}

/// The choices to try, best first: the walks asked for (else the device default, then the
/// full stack, then the wide layout), each in the storage asked for (else `preferred`,
/// then the other).
pub(crate) fn choices(opts: &OpenOptions, preferred: BvhStorage) -> Vec<Choice> {
    let storages = match opts.storage {
        Some(s) => vec![s],
        None => {
            let other = match preferred {
                BvhStorage::Buffers => BvhStorage::Textures,
                BvhStorage::Textures => BvhStorage::Buffers,
            };
            vec![preferred, other]
        }
    };
    let walk_sets: Vec<Vec<Traversal>> = if opts.traversals.is_empty() {
        // The stackless and short-stack walks read the same arrays: one stands for both.
        [
            Traversal::GPU_DEFAULT,
            Traversal::FullStack,
            Traversal::Wide,
        ]
        .into_iter()
        .fold(Vec::new(), |mut v, w| {
            if !v.contains(&vec![w]) {
                v.push(vec![w]);
            }
            v
        })
    } else {
        vec![opts.traversals.clone()]
    };
    walk_sets
        .into_iter()
        .flat_map(|walks| {
            storages.iter().map(move |&storage| Choice {
                walks: walks.clone(),
                storage,
            })
        })
        .collect()
}

/// Tries `choices` in order, going on only when one exceeds a limit: the first that
/// opens, with a sentence on what was refused before it; or the first choice's error.
pub(crate) fn first_that_fits<T>(
    choices: &[Choice],
    mut attempt: impl FnMut(&Choice) -> Result<T, TraceError>,
) -> Result<(T, Choice, Option<String>), TraceError> {
    let mut refused: Vec<(Choice, TraceError)> = Vec::new();
    for choice in choices {
        match attempt(choice) {
            Ok(t) => {
                let why = refused.first().map(|(c, e)| {
                    format!("{c} does not fit this device ({e}); using {choice} instead")
                });
                return Ok((t, choice.clone(), why));
            }
            Err(e) if exceeds_a_limit(&e) => refused.push((choice.clone(), e)),
            Err(e) => return Err(e),
        }
    }
    Err(refused
        .into_iter()
        .next()
        .map_or(TraceError::EmptyBvh, |(_, e)| e))
}

/// Checks that `tracer` runs every walk of `choice` (a full-stack walk on a deep tree is
/// refused here on some backends).
fn check_walks(tracer: &dyn Tracer, walks: &[Traversal]) -> Result<(), TraceError> {
    walks
        .iter()
        .try_for_each(|&w| tracer.supports(&TraceOptions::closest(w)))
}

/// [`open`] on a wgpu device the caller owns (an application's, eframe's): `opts.backend`,
/// `opts.adapter` and `opts.tuning` are the context's business and not read here.
pub fn open_on_wgpu(
    ctx: &GpuContext,
    bvh: &FlatBvh,
    opts: &OpenOptions,
) -> Result<Opened<'static>, TraceError> {
    let list = choices(opts, ctx.tuning().storage);
    let (gpu, choice, fallback) = first_that_fits(&list, |c| {
        let upload = UploadOptions {
            traversals: c.walks.clone(),
            storage: Some(c.storage),
        };
        let gpu = GpuBvh::upload(ctx, bvh, &upload)?;
        check_walks(&gpu, &c.walks)?;
        Ok(gpu)
    })?;
    Ok(Opened {
        device: gpu.device_name(),
        tracer: Box::new(gpu),
        backend: Backend::Wgpu,
        storage: Some(choice.storage),
        traversal: choice.walks[0],
        fallback,
        choice: None,
    })
}

/// [`open`] on a Vulkan context the caller owns (shared between many scenes): only
/// `opts.traversals` and `opts.storage` are read. The tree goes to storage buffers, and
/// its wide layout too when a wide walk is listed (collapsed for the upload when `bvh`
/// has none).
#[cfg(not(target_arch = "wasm32"))]
pub fn open_on_vulkan(
    ctx: &VkContext,
    bvh: &FlatBvh,
    opts: &OpenOptions,
) -> Result<Opened<'static>, TraceError> {
    let mut notes = Vec::new();
    if opts.storage == Some(BvhStorage::Textures) {
        notes.push("the Vulkan backend reads the tree from buffers only".to_string());
    }
    let plain = OpenOptions {
        storage: Some(BvhStorage::Buffers),
        ..opts.clone()
    };
    let list = choices(&plain, BvhStorage::Buffers);
    let (vk, choice, fallback) = first_that_fits(&list, |c| {
        let upload = UploadOptions {
            traversals: c.walks.clone(),
            storage: Some(c.storage),
        };
        let vk = VkBvh::upload(ctx, bvh, &upload)?;
        check_walks(&vk, &c.walks)?;
        Ok(vk)
    })?;
    notes.extend(fallback);
    Ok(Opened {
        device: vk.device_name(),
        tracer: Box::new(vk),
        backend: Backend::Vulkan,
        storage: Some(BvhStorage::Buffers),
        traversal: choice.walks[0],
        fallback: (!notes.is_empty()).then(|| notes.join("; ")),
        choice: None,
    })
}

/// [`open`] with ray queries on a wgpu device the caller opened with them
/// ([`bvhtrace_gpu::ContextOptions::ray_queries`]): only `opts.traversals` is read, for
/// [`Opened::traversal`] (the driver walks whatever it says).
#[cfg(not(target_arch = "wasm32"))]
pub fn open_on_ray_query(
    ctx: &GpuContext,
    bvh: &FlatBvh,
    opts: &OpenOptions,
) -> Result<Opened<'static>, TraceError> {
    let rq = bvhtrace_gpu::RayQueryBvh::upload(ctx, bvh)?;
    Ok(Opened {
        device: rq.device_name(),
        tracer: Box::new(rq),
        backend: Backend::RayQuery,
        storage: None,
        traversal: opts
            .traversals
            .first()
            .copied()
            .unwrap_or(Traversal::GPU_DEFAULT),
        fallback: None,
        choice: None,
    })
}

/// `tracer` with `opts`' filter and the CPU layout beside it ([`FastCpuTracer`]), boxed.
fn with_filter<'a, B>(tracer: CpuTracer<B>, opts: &OpenOptions) -> Box<dyn Tracer + 'a>
where
    B: Borrow<FlatBvh> + Send + Sync + 'a,
{
    match &opts.filter {
        Some(f) => Box::new(FastCpuTracer::new(tracer.with_filter(f.0.clone()))),
        None => Box::new(FastCpuTracer::new(tracer)),
    }
}

/// The CPU walks on `bvh`, in place unless a wide walk is asked for and the tree has no
/// wide layout (then on a copy with one), and the CPU layout for the full-stack traces it
/// takes.
fn open_cpu<'a, B>(
    bvh: B,
    opts: &OpenOptions,
    why: Option<String>,
) -> Result<Opened<'a>, TraceError>
where
    B: Borrow<FlatBvh> + Send + Sync + 'a,
{
    let walks = if opts.traversals.is_empty() {
        vec![Traversal::CPU_DEFAULT]
    } else {
        opts.traversals.clone()
    };
    let mut notes: Vec<String> = why.into_iter().collect();
    let tracer: Box<dyn Tracer + 'a> = if walks.iter().any(|w| w.is_wide())
        && bvh.borrow().wide().is_none()
    {
        notes.push("the wide walk traces a copy of the tree collapsed into the wide layout".into());
        with_filter(
            CpuTracer::new(Arc::new(bvh.borrow().clone().with_wide())),
            opts,
        )
    } else {
        with_filter(CpuTracer::new(bvh), opts)
    };
    check_walks(&*tracer, &walks)?;
    Ok(Opened {
        device: tracer.device_name(),
        tracer,
        backend: Backend::Cpu,
        storage: None,
        traversal: walks[0],
        fallback: (!notes.is_empty()).then(|| notes.join("; ")),
        choice: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn too_large(what: &'static str) -> TraceError {
        TraceError::TooLarge {
            buffer: what,
            bytes: 2,
            limit: 1,
            limit_name: "max_texture_dimension_2d",
        }
    }

    #[test]
    fn storages_are_tried_before_walks() {
        let list = choices(&OpenOptions::default(), BvhStorage::Textures);
        let seen: Vec<(Traversal, BvhStorage)> =
            list.iter().map(|c| (c.walks[0], c.storage)).collect();
        use BvhStorage::{Buffers, Textures};
        assert_eq!(
            seen,
            [
                (Traversal::GPU_DEFAULT, Textures),
                (Traversal::GPU_DEFAULT, Buffers),
                (Traversal::FullStack, Textures),
                (Traversal::FullStack, Buffers),
                (Traversal::Wide, Textures),
                (Traversal::Wide, Buffers),
            ]
        );
        // A walk or storage asked for is kept.
        let asked = OpenOptions::default()
            .with_traversal(Traversal::FullStack)
            .with_traversal(Traversal::Stackless)
            .with_storage(BvhStorage::Buffers);
        let list = choices(&asked, BvhStorage::Textures);
        assert_eq!(list.len(), 1);
        assert_eq!(list[0].walks, [Traversal::FullStack, Traversal::Stackless]);
    }

    #[test]
    fn the_escape_links_over_the_limit_fall_back_to_another_walk() {
        // Textures only: the escape texels are too many, as for a 27M-triangle scene.
        let opts = OpenOptions::default().with_storage(BvhStorage::Textures);
        let list = choices(&opts, BvhStorage::Textures);
        let (walk, choice, why) = first_that_fits(&list, |c| {
            if c.walks[0].needs_escapes() {
                Err(too_large("escape texels"))
            } else {
                Ok(c.walks[0])
            }
        })
        .expect("the full stack fits");
        assert_eq!(walk, Traversal::FullStack);
        assert_eq!(choice.storage, BvhStorage::Textures);
        let why = why.expect("the fallback is said");
        assert!(
            why.contains("stackless walk in texture storage")
                && why.contains("escape texels")
                && why.contains("full-stack walk"),
            "{why}"
        );
    }

    #[test]
    fn nothing_fits_names_the_limit_and_other_errors_stop() {
        let list = choices(&OpenOptions::default(), BvhStorage::Buffers);
        let mut tried = 0;
        let err = first_that_fits::<()>(&list, |_| {
            tried += 1;
            Err(too_large("nodes"))
        })
        .expect_err("nothing fits");
        assert_eq!(tried, list.len());
        assert!(
            err.to_string().contains("max_texture_dimension_2d"),
            "{err}"
        );
        let mut tried = 0;
        let err = first_that_fits::<()>(&list, |_| {
            tried += 1;
            Err(TraceError::DeviceLost { during: "a test" })
        })
        .expect_err("lost");
        assert_eq!(tried, 1, "a lost device is not a limit: {err}");
    }
}
