//! Opening a tracer: what is asked for ([`OpenOptions`]), what was opened ([`Opened`]), and
//! the ladder of storages and walks a device upload climbs when the tree exceeds a limit.

use std::borrow::Borrow;
use std::fmt;
use std::sync::Arc;

use bvhtrace_core::{FlatBvh, HitFilter, TraceOptions, Traversal};
use bvhtrace_engine::engine::BackendFeatures;
use bvhtrace_engine::walks;
use bvhtrace_engine::{AdapterChoice, BvhStorage, DriverTuning, TraceError, Tracer, UploadOptions};

use crate::{Backend, Device};

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
    /// fastest walk ([`DriverTuning::walk`] on a device, [`Traversal::CPU_DEFAULT`] on
    /// the CPU), settled before the upload so that only what it reads is uploaded, and
    /// another walk (the full stack, the wide layout) when it exceeds a device limit.
    /// [`Tracer::traversals`] says what the opened tracer answers.
    pub traversals: Vec<Traversal>,
    /// Buffers or textures on a device; `None`: the device's choice
    /// ([`DriverTuning::storage`]), and the other one when that exceeds a limit. A device
    /// without the storage asked for takes the other, and says so.
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
    /// The largest storage binding a device backend makes, when below the device's own
    /// (`None`: the device's): a tree larger than it is split into pages of at most this
    /// size (`bvhtrace_engine::pages`), as on a device with that limit. To try a browser's
    /// 128 MiB bindings natively, or the split on a small scene.
    pub max_binding_bytes: Option<u64>,
}

/// A [`HitFilter`] shared by the tracers that apply it ([`OpenOptions::filter`]).
#[derive(Clone)]
pub struct SharedFilter(pub Arc<dyn HitFilter + Send>);

impl fmt::Debug for SharedFilter {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
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
    /// Where the tree was put on the device; `None` on the CPU and for ray queries.
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
    /// The wgpu backend's tracer (our walks), for tracing from and into your own device
    /// buffers with no host copy: [`GpuBvh::record`](bvhtrace_gpu::GpuBvh::record)
    /// records the walk into your command encoder, reading your rays and writing your
    /// hits. `None` on the other backends.
    pub fn wgpu_bvh(&self) -> Option<&bvhtrace_gpu::GpuBvh> {
        self.tracer.as_any()?.downcast_ref()
    }

    /// One line: backend, device, storage and walk.
    pub fn summary(&self) -> String {
        if !self.backend.bit_for_bit() {
            return format!("{} on {}, the driver's walk", self.backend, self.device);
        }
        let storage = self
            .storage
            .map_or(String::new(), |s| format!(", {} storage", s.name()));
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

/// Opens the tracer `opts` asks for on `bvh` (borrowed, `Arc`-shared or owned: the CPU
/// walks trace it in place; a device backend uploads it and keeps no borrow).
///
/// [`Backend::Auto`] opens wgpu on the best Vulkan adapter (its ray queries where they run
/// in hardware), and the CPU walks when there is none, or when the scene exceeds the
/// device's limits every way; a named backend that cannot open is an error. On a device,
/// the walk is settled before the upload (the first of [`OpenOptions::traversals`], else
/// the backend's default), and when the tree exceeds a device limit in the preferred
/// storage, the other storage is tried, then (when no walk was asked for) the full-stack
/// walk, then the wide layout; when nothing fits, the error names every storage and walk
/// tried, and the limit each exceeded ([`TraceError::DoesNotFit`]). [`Opened::fallback`]
/// says what was tried instead.
///
/// To open many trees on one device, open the [`Device`] once and call [`Device::open`].
pub fn open<'a, B>(bvh: B, opts: &OpenOptions) -> Result<Opened<'a>, TraceError>
where
    B: Borrow<FlatBvh> + Send + Sync + 'a,
{
    Device::new(opts)?.open(bvh, opts)
}

/// True for the errors another storage, layout or walk, or another backend, may avoid.
pub(crate) fn exceeds_a_limit(e: &TraceError) -> bool {
    matches!(
        e,
        TraceError::TooLarge { .. }
            | TraceError::TooDeep { .. }
            | TraceError::LimitTooLow { .. }
            | TraceError::WideLayoutMissing { .. }
            | TraceError::DoesNotFit { .. }
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
        let storage = self.storage.name();
        write!(f, "the {} walk in {storage} storage", walks.join("/"))
    }
}

/// The storages to try, best first, with a sentence for each one left out: the one asked
/// for (else `preferred`, then the other), less those the device does not offer (a storage
/// asked for but not offered gives way to the other, said so).
fn storages(
    asked: Option<BvhStorage>,
    preferred: BvhStorage,
    features: &BackendFeatures,
    device: &str,
) -> (Vec<BvhStorage>, Vec<String>) {
    let offered = |s: BvhStorage| features.check_storage(s, || device.to_string());
    let wanted = match asked {
        Some(s) => vec![s],
        None => vec![preferred, preferred.other()],
    };
    let mut notes = Vec::new();
    let mut out: Vec<BvhStorage> = Vec::new();
    for s in wanted {
        match offered(s) {
            Ok(()) => out.push(s),
            Err(e) if asked.is_some() => {
                notes.push(format!("{e}; using {} storage", s.other().name()));
                out.push(s.other());
            }
            Err(e) => notes.push(e.to_string()),
        }
    }
    (out, notes)
}

/// The choices to try, best first: the walks asked for (else the device's default `walk`,
/// then each other walk that reads other arrays, in [`Traversal::ALL`]'s order: the full
/// stack, the stackless walk, the wide layout), each in the storages [`storages`] gives.
pub(crate) fn choices(opts: &OpenOptions, storages: &[BvhStorage], walk: Traversal) -> Vec<Choice> {
    let walk_sets: Vec<Vec<Traversal>> = if opts.traversals.is_empty() {
        let mut seen: Vec<&walks::Walk> = Vec::new();
        std::iter::once(walk)
            .chain(Traversal::ALL)
            .filter(|&t| {
                let w = walks::walk(t);
                let new = !seen.contains(&w);
                seen.push(w);
                new
            })
            .map(|t| vec![t])
            .collect()
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
/// opens, with a sentence on what was refused before it; when none does, the one refusal
/// as it is, or [`TraceError::DoesNotFit`] naming each (and `notes`: the storages the
/// device does not offer).
pub(crate) fn first_that_fits<T>(
    device: &str,
    choices: &[Choice],
    notes: &[String],
    mut attempt: impl FnMut(&Choice) -> Result<T, TraceError>,
) -> Result<(T, Choice, Option<String>), TraceError> {
    let mut refused: Vec<(Choice, TraceError)> = Vec::new();
    for choice in choices {
        // A tree too deep for a walk's stack is so in every storage.
        let too_deep = |(c, e): &(Choice, TraceError)| {
            c.walks == choice.walks && matches!(e, TraceError::TooDeep { .. })
        };
        if refused.iter().any(too_deep) {
            continue;
        }
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
    let deep = refused
        .first()
        .is_some_and(|(_, e)| matches!(e, TraceError::TooDeep { .. }));
    if refused.len() == 1 && (notes.is_empty() || deep) {
        return Err(refused.remove(0).1);
    }
    let mut tried: Vec<String> = refused.iter().map(|(c, e)| format!("{c}: {e}")).collect();
    tried.extend(notes.iter().cloned());
    Err(TraceError::DoesNotFit {
        device: device.to_string(),
        tried,
    })
}

/// Checks that `tracer` runs every walk of `walks` (a full-stack walk on a deep tree is
/// refused here on some backends).
pub(crate) fn check_walks(tracer: &dyn Tracer, walks: &[Traversal]) -> Result<(), TraceError> {
    walks
        .iter()
        .try_for_each(|&w| tracer.supports(&TraceOptions::closest(w)))
}

/// What an engine backend's device offers the ladder: its name, what its kernels can read
/// and its tuning (the storage it prefers, [`DriverTuning::storage`], and the walk,
/// [`DriverTuning::walk`]).
pub(crate) struct EngineDevice<'d> {
    pub(crate) backend: Backend,
    pub(crate) name: &'d str,
    pub(crate) features: BackendFeatures,
    pub(crate) tuning: DriverTuning,
}

/// Opens our walks on an engine backend's device: every choice of the ladder uploaded with
/// `upload` (that backend's upload of the tree, the same signature on each) until one
/// fits.
pub(crate) fn open_engine<T: Tracer + 'static>(
    device: &EngineDevice<'_>,
    opts: &OpenOptions,
    upload: impl Fn(&UploadOptions) -> Result<T, TraceError>,
) -> Result<Opened<'static>, TraceError> {
    let (storages, notes) = storages(
        opts.storage,
        device.tuning.storage,
        &device.features,
        device.name,
    );
    let list = choices(opts, &storages, device.tuning.walk);
    let (tracer, choice, fallback) = first_that_fits(device.name, &list, &notes, |c| {
        let upload_opts = UploadOptions {
            traversals: c.walks.clone(),
            storage: Some(c.storage),
        };
        let tracer = upload(&upload_opts)?;
        check_walks(&tracer, &c.walks)?;
        Ok(tracer)
    })?;
    // A storage asked for that the device lacks is said even when the other fitted.
    let asked_note = opts
        .storage
        .filter(|&s| s != choice.storage)
        .and(notes.first().cloned());
    let fallback = match (asked_note, fallback) {
        (Some(a), Some(b)) => Some(format!("{a}; {b}")),
        (a, b) => a.or(b),
    };
    Ok(Opened {
        device: tracer.device_name(),
        tracer: Box::new(tracer),
        backend: device.backend,
        storage: Some(choice.storage),
        traversal: choice.walks[0],
        fallback,
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
            storage: None,
        }
    }

    const BOTH: BackendFeatures = BackendFeatures {
        textures: true,
        vertex_attributes: true,
        f64: false,
    };

    #[test]
    fn storages_are_tried_before_walks() {
        let (tried, _) = storages(None, BvhStorage::Textures, &BOTH, "d");
        let list = choices(&OpenOptions::default(), &tried, Traversal::GPU_DEFAULT);
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
        let (tried, _) = storages(asked.storage, BvhStorage::Textures, &BOTH, "d");
        let list = choices(&asked, &tried, Traversal::GPU_DEFAULT);
        assert_eq!(list.len(), 1);
        assert_eq!(list[0].walks, [Traversal::FullStack, Traversal::Stackless]);
    }

    /// A device without texture storage is not offered it, and a storage asked for that
    /// it lacks gives way to the other, said so.
    #[test]
    fn storages_the_device_lacks_are_left_out_and_said() {
        let no_textures = BackendFeatures {
            textures: false,
            ..BOTH
        };
        let (s, notes) = storages(None, BvhStorage::Textures, &no_textures, "d");
        assert_eq!(s, [BvhStorage::Buffers]);
        assert!(notes[0].contains("texture storage"), "{notes:?}");
        let (s, notes) = storages(
            Some(BvhStorage::Textures),
            BvhStorage::Buffers,
            &no_textures,
            "d",
        );
        assert_eq!(s, [BvhStorage::Buffers]);
        assert!(notes[0].contains("using buffer storage"), "{notes:?}");
    }

    #[test]
    fn the_escape_links_over_the_limit_fall_back_to_another_walk() {
        // Textures only: the escape texels are too many, as for a 27M-triangle scene.
        let opts = OpenOptions::default().with_storage(BvhStorage::Textures);
        let list = choices(&opts, &[BvhStorage::Textures], Traversal::GPU_DEFAULT);
        let (walk, choice, why) = first_that_fits("d", &list, &[], |c| {
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
    fn nothing_fits_names_every_refusal_and_other_errors_stop() {
        let list = choices(
            &OpenOptions::default(),
            &BvhStorage::ALL,
            Traversal::GPU_DEFAULT,
        );
        let mut tried = 0;
        let notes = ["texture storage: none here".to_string()];
        let err = first_that_fits::<()>("the device", &list, &notes, |_| {
            tried += 1;
            Err(too_large("nodes"))
        })
        .expect_err("nothing fits");
        assert_eq!(tried, list.len());
        let text = err.to_string();
        assert!(
            matches!(&err, TraceError::DoesNotFit { tried, .. } if tried.len() == list.len() + 1),
            "{err:?}"
        );
        for c in &list {
            assert!(text.contains(&c.to_string()), "{text}");
        }
        assert!(text.contains("max_texture_dimension_2d") && text.contains("none here"));
        // One choice refused: its own error.
        let one = choices(
            &OpenOptions::default().with_traversal(Traversal::Wide),
            &[BvhStorage::Buffers],
            Traversal::GPU_DEFAULT,
        );
        let err = first_that_fits::<()>("d", &one, &[], |_| Err(too_large("nodes")));
        assert!(matches!(err, Err(TraceError::TooLarge { .. })), "{err:?}");
        let mut tried = 0;
        let err = first_that_fits::<()>("d", &list, &[], |_| {
            tried += 1;
            Err(TraceError::DeviceLost { during: "a test" })
        })
        .expect_err("lost");
        assert_eq!(tried, 1, "a lost device is not a limit: {err}");
    }
}
