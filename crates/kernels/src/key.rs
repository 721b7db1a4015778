//! What one trace job needs, and the pipeline built from exactly that.
//!
//! A [`KernelKey`] says what the job uses (the traversal, hence whether the escape
//! links are read; closest or any hit; the triangle test; counters; per-vertex attributes
//! the scene has and the job shades with) and is the key of each backend's pipeline
//! cache. From it come
//!
//! * the WGSL module ([`KernelKey::source`]): composed of only the files the job
//!   needs ([`ModuleSet`]): no escape-link binding or escape-link walk for the full stack, no
//!   `counters` binding unless counters are on, no attribute module for a positions-only
//!   scene, one entry point;
//! * the bindings that module declares ([`KernelKey::bindings`], checked against a
//!   naga reflection of the composed source by the tests);
//! * the upload ([`KernelKey::upload_bytes`]): the escape links only when read.
//!
//! Closest/any hit and the short-stack size stay override constants (folded when the
//! pipeline is created). `Composition::EverythingOn` (with the `bench-hooks` feature) composes every module instead (the
//! module [`crate::kernel_source`] returns), for comparison.

use std::borrow::Cow;

use bvhtrace_core::flat::{ESCAPE_BLOCK, OCTANTS};
use bvhtrace_core::{Precision, Query, Traversal};

use crate::UploadStats;
use crate::wgsl::{self as shaders, BvhStorage, RayInput};
use bvhtrace_core::TraceOptions;
use bvhtrace_core::traverse::MAX_SHORT_STACK;

/// Bytes of one block of escape links ([`PerElement::NodeBlock`]).
const ESCAPE_BLOCK_BYTES: u64 = (ESCAPE_BLOCK * OCTANTS * 4) as u64;

/// Bytes of one node of the binary layout (`FlatNode`) or of the wide one (`WideNode`).
fn node_bytes(wide: bool) -> u64 {
    if wide {
        std::mem::size_of::<bvhtrace_core::WideNode>() as u64
    } else {
        std::mem::size_of::<bvhtrace_core::FlatNode>() as u64
    }
}

/// Blocks of escape links for `nodes` nodes.
fn escape_blocks(nodes: u64) -> u64 {
    nodes.div_ceil(ESCAPE_BLOCK as u64)
}

/// `bvh_buffers_escapes.wgsl`.
const BVH_BUFFERS_ESCAPES_WGSL: &str = include_str!("../shaders/bvh_buffers_escapes.wgsl");
/// `bvh_textures_escapes.wgsl`.
const BVH_TEXTURES_ESCAPES_WGSL: &str = include_str!("../shaders/bvh_textures_escapes.wgsl");
/// `entry_counters.wgsl`: the `counters` binding, composed only when counters are on.
const ENTRY_COUNTERS_WGSL: &str = include_str!("../shaders/entry_counters.wgsl");
/// `attribute_normals.wgsl`: per-vertex normals, composed only when the scene has them and
/// the job shades with them.
const ATTRIBUTE_NORMALS_WGSL: &str = include_str!("../shaders/attribute_normals.wgsl");
/// `bvh_instances.wgsl` / `bvh_no_instances.wgsl`: the instances binding of a two-level
/// BVH, or the same names for one mesh.
pub(crate) const BVH_INSTANCES_WGSL: (&str, &str) = (
    "bvh_instances.wgsl",
    include_str!("../shaders/bvh_instances.wgsl"),
);
pub(crate) const BVH_NO_INSTANCES_WGSL: (&str, &str) = (
    "bvh_no_instances.wgsl",
    include_str!("../shaders/bvh_no_instances.wgsl"),
);

/// `traverse_wide.wgsl`: the wide walk.
/// `bvh_alpha_masks.wgsl`: the masks binding (5) and `bvh_alpha_accept`.
pub(crate) const BVH_ALPHA_MASKS_WGSL: (&str, &str) = (
    "bvh_alpha_masks.wgsl",
    include_str!("../shaders/bvh_alpha_masks.wgsl"),
);
/// `candidate.wgsl`: `BvhCandidate`, what a library's filter sees.
const CANDIDATE_WGSL: (&str, &str) = ("candidate.wgsl", include_str!("../shaders/candidate.wgsl"));
/// Where `traverse_common.wgsl`'s leaf visit takes the candidate tests of
/// [`ModuleSet::masks`] and [`ModuleSet::filter`].
const ACCEPT_MARK: &str = "/*BVH_ACCEPT*/";

const TRAVERSE_WIDE_WGSL: (&str, &str) = (
    "traverse_wide.wgsl",
    include_str!("../shaders/traverse_wide.wgsl"),
);
/// `entry_walk.wgsl`: every entry point, specialised by [`EntryPoint::source`].
pub(crate) const ENTRY_WALK_WGSL: &str = include_str!("../shaders/entry_walk.wgsl");

/// One entry point: `entry_walk.wgsl` specialised with its name, its walk's call and
/// what it stores, so the entry points share one file and differ only in their walk.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct EntryPoint {
    /// The name [`KernelKey::entry_point`] gives.
    name: &'static str,
    /// How [`ModuleSet::files`] lists it.
    label: &'static str,
    /// The walk's call on ray `i` of the batch, with invocation `lid`'s stack.
    walk: &'static str,
    /// Writes the counters as well (needs `entry_counters.wgsl`).
    counted: bool,
}

impl EntryPoint {
    /// The entry point's WGSL.
    fn source(&self) -> String {
        let store = if self.counted {
            "bvh_store_counted"
        } else {
            "bvh_store_hits_only"
        };
        ENTRY_WALK_WGSL
            .replace("BVH_ENTRY_POINT", self.name)
            .replace("BVH_STORE", store)
            .replace("BVH_WALK", self.walk)
    }
}

/// The walks that have entry points, in composition order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Walk {
    FullStack,
    ShortStack,
    Wide,
}

/// Declares the two entry points (hits only, counted) of a walk.
macro_rules! entry_points {
    ($stem:literal, $walk:literal) => {
        [
            EntryPoint {
                name: concat!("bvh_trace_", $stem, "_main"),
                label: concat!("entry_walk.wgsl: bvh_trace_", $stem, "_main"),
                walk: $walk,
                counted: false,
            },
            EntryPoint {
                name: concat!("bvh_trace_", $stem, "_counted"),
                label: concat!("entry_walk.wgsl: bvh_trace_", $stem, "_counted"),
                walk: $walk,
                counted: true,
            },
        ]
    };
}

impl Walk {
    /// The walk's entry points: `[hits only, counted]`.
    fn entry_points(self) -> [EntryPoint; 2] {
        match self {
            Walk::FullStack => entry_points!(
                "full_stack",
                "bvh_trace_full_stack(bvh_load_ray(i), BVH_ANY_HIT, lid)"
            ),
            Walk::ShortStack => entry_points!(
                "short_stack",
                "bvh_trace_short_stack(bvh_load_ray(i), BVH_ANY_HIT, BVH_SHORT_STACK_SIZE, lid)"
            ),
            Walk::Wide => {
                entry_points!("wide", "bvh_trace_wide(bvh_load_ray(i), BVH_ANY_HIT, lid)")
            }
        }
    }

    /// The walk of `traversal`.
    fn of(traversal: Traversal) -> Walk {
        match traversal {
            Traversal::FullStack => Walk::FullStack,
            Traversal::Stackless | Traversal::ShortStack(_) => Walk::ShortStack,
            Traversal::Wide => Walk::Wide,
        }
    }
}

impl BvhStorage {
    /// The WGSL file declaring this storage's escape-link binding and `load_escape`.
    pub fn escapes_wgsl(&self) -> (&'static str, &'static str) {
        match self {
            BvhStorage::Buffers => ("bvh_buffers_escapes.wgsl", BVH_BUFFERS_ESCAPES_WGSL),
            BvhStorage::Textures => ("bvh_textures_escapes.wgsl", BVH_TEXTURES_ESCAPES_WGSL),
        }
    }
}

/// Optional per-vertex data. As a scene's content, what it has; as a job's, what it shades
/// with; [`VertexAttributes::needed`] is what a pipeline composes in and uploads.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct VertexAttributes {
    /// Per-vertex normals (glTF `NORMAL`), for smooth shading (`attribute_normals.wgsl`).
    pub normals: bool,
}

impl VertexAttributes {
    /// Positions only.
    pub const NONE: VertexAttributes = VertexAttributes { normals: false };

    /// What a pipeline needs: the attributes the scene has *and* the job uses.
    pub fn needed(scene_has: VertexAttributes, job_uses: VertexAttributes) -> VertexAttributes {
        VertexAttributes {
            normals: scene_has.normals && job_uses.normals,
        }
    }
}

/// How a pipeline's module is composed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum Composition {
    /// Only the files the job needs (the default).
    #[default]
    Specialised,
    /// Every traversal, the escape links and every entry point, counted or not
    /// ([`crate::kernel_source`]): the baseline the benchmark compares against. A
    /// benchmark hook: only with the `bench-hooks` feature (off by default).
    #[cfg(feature = "bench-hooks")]
    EverythingOn,
}

/// Which entry points a module holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Entries {
    /// None: the traversal library ([`crate::wgsl_library`]).
    None,
    /// The hits-only entry point of each traversal composed in.
    Plain,
    /// The counted entry point of each traversal composed in, and the `counters` binding.
    Counted,
    /// Both.
    All,
}

/// The WGSL files one module is composed of.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ModuleSet {
    /// Where both layouts' bindings are read from: the nodes file
    /// ([`BvhStorage::wgsl`], or [`BvhStorage::wide_wgsl`] with `wide`) and the triangles'
    /// ([`BvhStorage::triangles_wgsl`]).
    pub storage: BvhStorage,
    /// The triangle test ([`shaders::triangle_wgsl`]).
    pub precision: Precision,
    /// The escape-link binding (`bvh_*_escapes.wgsl`).
    pub escapes: bool,
    /// `traverse_full_stack.wgsl`.
    pub full_stack: bool,
    /// `traverse_short_stack.wgsl` (needs `escapes`).
    pub short_stack: bool,
    /// The wide layout ([`BvhStorage::wide_wgsl`]) and its walk (`traverse_wide.wgsl`), in
    /// place of the binary layout's nodes and walks: binding 0 holds wide nodes, so a
    /// module has one layout or the other (`escapes`, `full_stack` and `short_stack` are
    /// then ignored).
    pub wide: bool,
    /// Attribute modules.
    pub attributes: VertexAttributes,
    /// The instances binding (`bvh_instances.wgsl`), for a two-level BVH.
    pub instances: bool,
    /// Entry points (with `entry.wgsl`, and `entry_counters.wgsl` when counted).
    pub entries: Entries,
    /// Where the entry points read the rays (`entry_rays_*.wgsl`).
    pub rays: shaders::RayInput,
    /// The alpha masks (`bvh_alpha_masks.wgsl`, binding 5), asked about every candidate
    /// that would become the hit.
    pub masks: bool,
    /// The name of a WGSL function of yours, `fn(BvhCandidate) -> bool`, asked about every
    /// candidate that would become the hit (after the masks), with `candidate.wgsl`.
    pub filter: Option<&'static str>,
}

impl ModuleSet {
    /// Everything of the binary layout but attributes: the library and, with `entries`,
    /// the kernels.
    pub fn everything(storage: BvhStorage, precision: Precision, entries: Entries) -> ModuleSet {
        ModuleSet {
            storage,
            precision,
            escapes: true,
            full_stack: true,
            short_stack: true,
            wide: false,
            attributes: VertexAttributes::NONE,
            instances: false,
            entries,
            rays: shaders::RayInput::Buffer,
            masks: false,
            filter: None,
        }
    }

    /// Everything of the wide layout but attributes, in buffers: its bindings, its walk
    /// and, with `entries`, its kernels. Set `storage` for textures
    /// ([`ModuleSet::wide_in`]).
    pub fn wide(precision: Precision, entries: Entries) -> ModuleSet {
        ModuleSet::wide_in(BvhStorage::Buffers, precision, entries)
    }

    /// [`ModuleSet::wide`] with the wide layout read from `storage`.
    pub fn wide_in(storage: BvhStorage, precision: Precision, entries: Entries) -> ModuleSet {
        ModuleSet {
            escapes: false,
            full_stack: false,
            short_stack: false,
            wide: true,
            ..ModuleSet::everything(storage, precision, entries)
        }
    }

    /// True when the module declares the `counters` binding.
    pub fn has_counters(&self) -> bool {
        matches!(self.entries, Entries::Counted | Entries::All)
    }

    /// The walks composed in, in composition order.
    fn walks(&self) -> Vec<Walk> {
        if self.wide {
            return vec![Walk::Wide];
        }
        [
            (self.full_stack, Walk::FullStack),
            (self.short_stack, Walk::ShortStack),
        ]
        .into_iter()
        .filter_map(|(on, w)| on.then_some(w))
        .collect()
    }

    /// The files, in composition order, as `(file name, source)`; an entry point is
    /// `entry_walk.wgsl` specialised for its walk, named after it, and the leaf visit
    /// (`traverse_common.wgsl`) has the masks' and filter's tests when there are some.
    pub fn files(&self) -> Vec<(&'static str, Cow<'static, str>)> {
        let mut out = self.unspecialised_files();
        if self.masks || self.filter.is_some() {
            for (name, src) in &mut out {
                if *name == "traverse_common.wgsl" {
                    *src = src.replace(ACCEPT_MARK, &self.accept_test()).into();
                }
            }
        }
        out
    }

    /// [`ModuleSet::files`] before the leaf visit takes the candidate tests.
    fn unspecialised_files(&self) -> Vec<(&'static str, Cow<'static, str>)> {
        let wide = self.wide;
        let (full, short) = (self.full_stack && !wide, self.short_stack && !wide);
        let mut out: Vec<(&'static str, Cow<'static, str>)> = Vec::with_capacity(20);
        let mut push = |(name, src): (&'static str, &'static str)| out.push((name, src.into()));
        for (i, &(name, src)) in shaders::SHADER_FILES.iter().enumerate() {
            match name {
                "traverse_stack.wgsl" if !(full || short || wide) => {}
                "traverse_full_stack.wgsl" if !full => {}
                "traverse_short_stack.wgsl" => {
                    if short {
                        push((name, src));
                    }
                    if wide {
                        push(TRAVERSE_WIDE_WGSL);
                    }
                }
                "triangle.wgsl" => push(shaders::triangle_wgsl(self.precision)),
                _ => push((name, src)),
            }
            if i == 0 {
                push(if wide {
                    self.storage.wide_wgsl()
                } else {
                    self.storage.wgsl()
                });
                push(self.storage.triangles_wgsl());
                if self.escapes && !wide {
                    push(self.storage.escapes_wgsl());
                }
                push(if self.instances {
                    BVH_INSTANCES_WGSL
                } else {
                    BVH_NO_INSTANCES_WGSL
                });
                if self.masks {
                    push(BVH_ALPHA_MASKS_WGSL);
                }
                if self.filter.is_some() {
                    push(CANDIDATE_WGSL);
                }
            }
        }
        if self.attributes.normals {
            push(("attribute_normals.wgsl", ATTRIBUTE_NORMALS_WGSL));
        }
        if self.entries == Entries::None {
            return out;
        }
        push(("entry.wgsl", shaders::ENTRY_WGSL));
        push(self.rays.wgsl());
        if self.has_counters() {
            push(("entry_counters.wgsl", ENTRY_COUNTERS_WGSL));
        }
        let plain = matches!(self.entries, Entries::Plain | Entries::All);
        let counted = self.has_counters();
        for walk in self.walks() {
            for ep in walk.entry_points() {
                if (ep.counted && counted) || (!ep.counted && plain) {
                    out.push((ep.label, ep.source().into()));
                }
            }
        }
        out
    }

    /// What the leaf visit adds to its test of a candidate: the masks', then the filter's.
    fn accept_test(&self) -> String {
        let mut s = String::new();
        if self.masks {
            s.push_str(" && bvh_alpha_accept(tri.prim, h.u, h.v)");
        }
        if let Some(f) = self.filter {
            s.push_str(&format!(" && {f}(bvh_candidate(prim, tri.prim, h))"));
        }
        s
    }

    /// The composed WGSL, the BVH bindings (and attribute bindings) in `@group(bvh_group)`.
    pub fn compose(&self, bvh_group: u32) -> String {
        let mut s = String::with_capacity(32 * 1024);
        let group = format!("@group({bvh_group})");
        for (name, src) in self.files() {
            s.push_str("// ---- ");
            s.push_str(name);
            s.push_str(" ----\n");
            let rebind =
                bvh_group != 0 && (name.starts_with("bvh_") || name.starts_with("attribute_"));
            if rebind {
                s.push_str(&src.replace("@group(0)", &group));
            } else {
                s.push_str(&src);
            }
            s.push('\n');
        }
        s
    }
}

/// What one binding holds, per element.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PerElement {
    /// One element per BVH node.
    Node,
    /// One element per block of [`bvhtrace_core::flat::ESCAPE_BLOCK`] nodes (the last one
    /// padded): the escape links.
    NodeBlock,
    /// One element per triangle.
    Triangle,
    /// One element per instance of a two-level BVH.
    Instance,
    /// One element per ray of the batch.
    Ray,
    /// One word of the alpha masks (`MaskTables::words`): as many as the tables have,
    /// not counted by [`KernelKey::declared_bvh_bytes`].
    MaskWord,
}

/// One binding a composed module declares.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct BindingInfo {
    /// Bind group.
    pub group: u32,
    /// Binding number.
    pub binding: u32,
    /// The WGSL variable's name.
    pub name: &'static str,
    /// Bytes per element (for textures: texels per element x texel bytes, row padding
    /// excluded).
    pub element_bytes: u64,
    /// What the elements count.
    pub per: PerElement,
    /// Uploaded once with the BVH (group 0) rather than per batch.
    pub uploaded: bool,
}

/// Everything that decides one trace kernel: which files are composed, which entry point
/// runs and which override constants it gets. The key of a backend's pipeline cache.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct KernelKey {
    /// Where the BVH (either layout: the wide walk's nodes and triangles too) is read
    /// from.
    pub storage: BvhStorage,
    /// The walk; a short stack's size is clamped to `1..=MAX_SHORT_STACK` by
    /// [`KernelKey::new`], as the CPU walk clamps it.
    pub traversal: Traversal,
    /// Closest or any hit (`ANY_HIT`).
    pub query: Query,
    /// The triangle test composed into the module ([`shaders::triangle_wgsl`]).
    pub precision: Precision,
    /// The counted entry point and the `counters` binding.
    pub counters: bool,
    /// Where the entry point reads the rays and writes the hits.
    pub rays: RayInput,
    /// `PARALLEL_RAYS` (`box.wgsl`): some ray of the batch may have a zero direction
    /// component ([`bvhtrace_core::intersect::is_parallel_to_a_slab`]). True unless the
    /// batch is known to have none ([`KernelKey::for_rays`]).
    pub parallel_rays: bool,
    /// Per-vertex attributes composed in ([`VertexAttributes::needed`]).
    pub attributes: VertexAttributes,
    /// The BVH has two levels: the instances binding and the walks' instance code.
    pub instances: bool,
    /// The rays' visibility mask (`BVH_RAY_MASK`, read only with `instances`).
    pub mask: u8,
    /// The BVH has alpha masks (`FlatBvh::masks`): their binding and test.
    pub masks: bool,
    /// Only what is needed, or everything.
    pub composition: Composition,
}

impl KernelKey {
    /// The specialised kernel tracing as `opts` says with the BVH (either layout) in
    /// `storage`: rays in buffers, the parallel path kept, positions only.
    pub fn new(storage: BvhStorage, opts: &TraceOptions) -> KernelKey {
        let traversal = match opts.traversal {
            Traversal::ShortStack(k) => Traversal::ShortStack(k.clamp(1, MAX_SHORT_STACK)),
            t => t,
        };
        KernelKey {
            storage,
            traversal,
            query: opts.query,
            precision: opts.precision,
            counters: opts.counters,
            rays: RayInput::Buffer,
            parallel_rays: true,
            attributes: VertexAttributes::NONE,
            instances: false,
            mask: opts.mask,
            masks: false,
            composition: Composition::Specialised,
        }
    }

    /// The kernel for a job: as [`KernelKey::new`], with the rays read as the convenience
    /// trace of that storage uploads them ([`RayInput::for_storage`]) and the attributes
    /// the scene has and the job uses.
    pub fn for_job(
        storage: BvhStorage,
        opts: &TraceOptions,
        scene_has: VertexAttributes,
        job_uses: VertexAttributes,
    ) -> KernelKey {
        KernelKey {
            rays: RayInput::for_storage(storage),
            attributes: VertexAttributes::needed(scene_has, job_uses),
            ..Self::new(storage, opts)
        }
    }

    /// The options this kernel traces with.
    pub fn options(&self) -> TraceOptions {
        TraceOptions {
            traversal: self.traversal,
            query: self.query,
            precision: self.precision,
            counters: self.counters,
            mask: self.mask,
        }
    }

    /// The same key for a BVH with instances (`FlatBvh::is_instanced`) or without.
    pub fn with_instances(self, instances: bool) -> KernelKey {
        KernelKey { instances, ..self }
    }

    /// The same key for a BVH with alpha masks (`FlatBvh::masks`) or without.
    pub fn with_masks(self, masks: bool) -> KernelKey {
        KernelKey { masks, ..self }
    }

    /// The same key reading its rays from `rays`.
    pub fn with_rays(self, rays: RayInput) -> KernelKey {
        KernelKey { rays, ..self }
    }

    /// The same key, composed as `composition` says.
    pub fn with_composition(self, composition: Composition) -> KernelKey {
        KernelKey {
            composition,
            ..self
        }
    }

    /// The same key specialised for `rays`: the box test's parallel path is compiled out
    /// when none of them has a zero direction component.
    pub fn for_rays(self, rays: &[bvhtrace_core::Ray]) -> KernelKey {
        let parallel_rays = rays
            .iter()
            .any(|r| bvhtrace_core::intersect::is_parallel_to_a_slab(glam::Vec3::from(r.dir)));
        KernelKey {
            parallel_rays,
            ..self
        }
    }

    /// True when the kernel walks a short stack (or none) and so reads the escape links.
    pub fn needs_escapes(&self) -> bool {
        self.traversal.needs_escapes()
    }

    /// The short stack's size (`SHORT_STACK_SIZE`): 0 for the stackless walk, `None` for
    /// the full stack.
    fn short_stack_size(&self) -> Option<u32> {
        match self.traversal {
            Traversal::FullStack | Traversal::Wide => None,
            Traversal::Stackless => Some(0),
            Traversal::ShortStack(k) => Some(k.clamp(1, MAX_SHORT_STACK)),
        }
    }

    /// The entry point's name: `bvh_trace_{full_stack,short_stack,wide}_{main,counted}`.
    pub fn entry_point(&self) -> &'static str {
        Walk::of(self.traversal).entry_points()[usize::from(self.counters)].name
    }

    /// The override constants the key sets, as wgpu and naga take them. A backend adds
    /// `BVH_TRIP_LIMIT` and `BVH_DISPATCH_THREADS` from its [`crate::DriverTuning`].
    pub fn constants(&self) -> Vec<(&'static str, f64)> {
        let flag = |b: bool| if b { 1.0 } else { 0.0 };
        let mut c = vec![
            ("BVH_ANY_HIT", flag(self.query == Query::Any)),
            ("BVH_PARALLEL_RAYS", flag(self.parallel_rays)),
        ];
        if self.instances {
            c.push(("BVH_RAY_MASK", f64::from(self.mask)));
        }
        if let Some(k) = self.short_stack_size() {
            c.push(("BVH_SHORT_STACK_SIZE", f64::from(k)));
        }
        c
    }

    /// Every key the tests validate for `storage`: each walk (full stack, stackless,
    /// short stack of size `k`, wide) x query x counters x one mesh or two levels. The
    /// wide keys are the same for every `k` (no ring).
    pub fn all_for_k(storage: BvhStorage, k: u32) -> Vec<KernelKey> {
        let mut v = Vec::new();
        for traversal in [
            Traversal::FullStack,
            Traversal::Stackless,
            Traversal::ShortStack(k),
            Traversal::Wide,
        ] {
            for query in [Query::Closest, Query::Any] {
                for counters in [false, true] {
                    for instances in [false, true] {
                        let opts = TraceOptions::new(traversal, query).with_counters(counters);
                        v.push(KernelKey::new(storage, &opts).with_instances(instances));
                    }
                }
            }
        }
        v
    }

    /// The files the module is composed of.
    pub fn module_set(&self) -> ModuleSet {
        match self.composition {
            // A module holds one layout: everything of the wide one for a wide key.
            #[cfg(feature = "bench-hooks")]
            Composition::EverythingOn => ModuleSet {
                rays: self.rays,
                instances: self.instances,
                masks: self.masks,
                ..if self.traversal.is_wide() {
                    ModuleSet::wide_in(self.storage, self.precision, Entries::All)
                } else {
                    ModuleSet::everything(self.storage, self.precision, Entries::All)
                }
            },
            Composition::Specialised => ModuleSet {
                storage: self.storage,
                precision: self.precision,
                escapes: self.needs_escapes(),
                full_stack: self.traversal == Traversal::FullStack,
                short_stack: self.needs_escapes(),
                wide: self.traversal.is_wide(),
                attributes: self.attributes,
                instances: self.instances,
                entries: if self.counters {
                    Entries::Counted
                } else {
                    Entries::Plain
                },
                rays: self.rays,
                masks: self.masks,
                filter: None,
            },
        }
    }

    /// The composed module (BVH in group [`shaders::BVH_GROUP`]).
    pub fn source(&self) -> String {
        self.module_set().compose(shaders::BVH_GROUP)
    }

    /// Every binding the module declares, in (group, binding) order. The pipeline binds
    /// those its entry point reads (all of them for [`Composition::Specialised`]).
    pub fn bindings(&self) -> Vec<BindingInfo> {
        let set = self.module_set();
        let textures = set.storage == BvhStorage::Textures;
        let mut b = Vec::new();
        let bvh = |binding, name, element_bytes, per| BindingInfo {
            group: shaders::BVH_GROUP,
            binding,
            name,
            element_bytes,
            per,
            uploaded: true,
        };
        let batch = |binding, name, element_bytes| BindingInfo {
            group: shaders::BATCH_GROUP,
            binding,
            name,
            element_bytes,
            per: PerElement::Ray,
            uploaded: false,
        };
        let (nodes, tris, escapes) = if set.wide && textures {
            ("bvh_wide_node_texels", "bvh_triangle_texels", "")
        } else if set.wide {
            ("bvh_wide_nodes", "bvh_triangles", "")
        } else if textures {
            (
                "bvh_node_texels",
                "bvh_triangle_texels",
                "bvh_escape_texels",
            )
        } else {
            ("bvh_nodes", "bvh_triangles", "bvh_escapes")
        };
        b.push(bvh(0, nodes, node_bytes(set.wide), PerElement::Node));
        b.push(bvh(1, tris, 48, PerElement::Triangle));
        if set.escapes && !set.wide {
            b.push(bvh(2, escapes, ESCAPE_BLOCK_BYTES, PerElement::NodeBlock));
        }
        if set.attributes.normals {
            b.push(bvh(3, "vertex_normals", 48, PerElement::Triangle));
        }
        if set.instances {
            b.push(bvh(4, "bvh_instances", 64, PerElement::Instance));
        }
        if set.masks {
            b.push(bvh(5, "bvh_masks", 4, PerElement::MaskWord));
        }
        if set.entries != Entries::None {
            let (rays, hits) = match set.rays {
                RayInput::Buffer => ("rays", "hits"),
                RayInput::Texture => ("ray_texels", "hit_texels"),
            };
            b.push(batch(0, rays, crate::plan::RAY_BYTES));
            b.push(batch(1, hits, crate::plan::HIT_BYTES));
            if set.has_counters() {
                b.push(batch(2, "counters", crate::plan::COUNTERS_BYTES));
            }
        }
        b
    }

    /// Bytes the BVH bindings declare for a tree of `nodes` nodes, `triangles`
    /// triangles and `instances` instances (0 for one mesh): what a [`BvhStorage::Buffers`]
    /// upload for this key holds, the alpha masks' words aside (texture uploads add row padding,
    /// [`KernelKey::upload_bytes`]). For a [`Traversal::Wide`] key, `nodes` counts the
    /// wide tree's 80-byte nodes (`WideBvh::nodes`).
    pub fn declared_bvh_bytes(&self, nodes: u64, triangles: u64, instances: u64) -> u64 {
        self.bindings()
            .iter()
            .filter(|b| b.uploaded)
            .map(|b| {
                b.element_bytes
                    * match b.per {
                        PerElement::Node => nodes,
                        PerElement::NodeBlock => escape_blocks(nodes),
                        PerElement::Triangle => triangles,
                        PerElement::Instance => instances,
                        PerElement::Ray | PerElement::MaskWord => 0,
                    }
            })
            .sum()
    }

    /// What an upload for this key holds for a tree of `nodes` nodes, `triangles`
    /// triangles and `instances` instances (`upload_ms` 0): the bindings' bytes
    /// ([`KernelKey::declared_bvh_bytes`]), plus, for textures taller than one row, the
    /// padding of their last row of [`shaders::TEXEL_ROW`] texels. For a
    /// [`Traversal::Wide`] key, `nodes` counts the wide tree's nodes: 80 bytes each, five
    /// texels in textures.
    pub fn upload_bytes(&self, nodes: u64, triangles: u64, instances: u64) -> UploadStats {
        let set = self.module_set();
        let sized = |elements: u64, element_bytes: u64, texels_per: u64, texel_bytes: u64| match set
            .storage
        {
            BvhStorage::Buffers => elements * element_bytes,
            BvhStorage::Textures => {
                let (row, texels) = (u64::from(shaders::TEXEL_ROW), elements * texels_per);
                if texels <= row {
                    texels.max(1) * texel_bytes
                } else {
                    texels.div_ceil(row) * row * texel_bytes
                }
            }
        };
        UploadStats {
            storage: set.storage,
            nodes_bytes: sized(nodes, node_bytes(set.wide), node_bytes(set.wide) / 16, 16),
            triangles_bytes: sized(triangles, 48, 3, 16),
            escapes_bytes: if set.escapes && !set.wide {
                sized(
                    escape_blocks(nodes),
                    ESCAPE_BLOCK_BYTES,
                    ESCAPE_BLOCK_BYTES / 4,
                    4,
                )
            } else {
                0
            },
            instances_bytes: if set.instances { instances * 64 } else { 0 },
            masks_bytes: 0,
            upload_ms: 0.0,
        }
    }

    /// What was included, in words, for listings: the query, the walk, and each optional
    /// part present (`escape-links`, `counters`, `vertex-normals`, `everything-on`).
    pub fn names(&self) -> Vec<&'static str> {
        let set = self.module_set();
        let mut n = vec![match self.query {
            Query::Any => "any-hit",
            Query::Closest => "closest-hit",
        }];
        n.push(self.traversal.name());
        if set.escapes {
            n.push("escape-links");
        }
        if self.counters {
            n.push("counters");
        }
        if set.attributes.normals {
            n.push("vertex-normals");
        }
        if set.instances {
            n.push("instances");
        }
        if set.masks {
            n.push("alpha-masks");
        }
        #[cfg(feature = "bench-hooks")]
        if self.composition == Composition::EverythingOn {
            n.push("everything-on");
        }
        n
    }
}
