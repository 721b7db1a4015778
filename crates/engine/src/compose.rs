//! The kernels' WGSL, composed at load time from the files of `shaders/` ([`crate::shaders`]),
//! one file per concern, and specialised per pipeline with override constants.
//!
//! | file | concern | CPU twin |
//! |---|---|---|
//! | `types.wgsl` | `BvhNode`, `BvhWideNode`, `BvhTriangle`, `BvhRay`, `BvhHit`, `BvhCounters`, `BvhTraceResult` | `bvhtrace_core::{FlatNode, WideNode, FlatTriangle, Ray, Hit, Counters}` |
//! | `bvh_buffers.wgsl` or `bvh_textures.wgsl` | the binary layout's node binding and fetch functions ([`BvhStorage`]) | `FlatBvh` |
//! | `bvh_buffers_wide.wgsl` or `bvh_textures_wide.wgsl` | the wide layout's nodes (binding 0), in their place for the wide walk | `WideBvh` |
//! | `bvh_buffers_triangles.wgsl` or `bvh_textures_triangles.wgsl` | the triangles (binding 1) of either layout; for textures, the texel addressing too | `FlatBvh::triangles`, `WideBvh::triangles` |
//! | `bvh_buffers_escapes.wgsl` or `bvh_textures_escapes.wgsl` | the escape links (binding 2), only for the walks that read them | `FlatBvh::escapes` |
//! | `bvh_instances.wgsl` or `bvh_no_instances.wgsl` | the instances (binding 4) of a two-level BVH, or the same names for one mesh | `FlatBvh::instances` |
//! | `bvh_alpha_masks.wgsl` | the alpha masks (binding 5), only for a masked tree | `MaskTables::accept` |
//! | `ray.wgsl` | validity, `bvh_safe_inverse`, `bvh_prepare_ray`, `bvh_octant` | `Ray::is_valid`, `PreparedRay::new`, `flat::octant` |
//! | `surface.wgsl` | `bvh_offset_ray_origin`, for secondary rays | `surface::offset_ray_origin` |
//! | `box.wgsl` | conservative slab test | `intersect::intersect_box` |
//! | `triangle_hit.wgsl` | `BvhTriHit`, what every triangle test returns | `intersect::TriHit` |
//! | `triangle.wgsl` (or a [`Precision`] variant, [`triangle_wgsl`]) | watertight triangle test | `intersect::intersect_triangle` |
//! | `traverse_common.wgsl` | hit rule, leaf visit | `traverse::visit_leaf` |
//! | `traverse_instances.wgsl` | entering and leaving instances of a two-level BVH (folded away for one mesh) | `traverse::Space` |
//! | `traverse_stack.wgsl` | the per-lane stacks in workgroup memory | `Vec` / the ring of `traverse::short_stack` |
//! | each walk's file ([`crate::walks::WALKS`]) | `bvh_trace_full_stack`, `bvh_trace_short_stack` (k = 0: stackless), `bvh_trace_wide` | `traverse::full_stack`, `short_stack`, `wide` |
//! | `library.wgsl` | only in a user's library ([`crate::wgsl_library`]) | `Hit::surface`, `TraceOutput::instance_hit` |
//! | `attribute_normals.wgsl` | per-vertex normals, only when the scene has them and the job uses them | - |
//! | `entry.wgsl` | what the entry points share: the overrides, `bvh_ray_index` | `traverse::trace_rays` |
//! | `entry_rays_buffer.wgsl` or `entry_rays_texture.wgsl` | where the rays come from and the hits go ([`RayInput`]) | - |
//! | `entry_counters.wgsl` | the `counters` binding, only when counters are on | `trace_rays` with counters |
//! | `entry_walk.wgsl` | every entry point, specialised per walk and output | |
//!
//! A [`ModuleSet`] says which files one module holds; [`crate::KernelKey`] picks only what
//! one pipeline needs, [`kernel_source`] composes every binary walk and entry point (the
//! everything-on module), and the library of a user's shader composes one walk with no
//! entry point. Every name the WGSL declares starts with `bvh_`, `Bvh` or `BVH_`, so a
//! library composes with a user's shader. Nothing is copied between variants: the query
//! and a short stack's size are pipeline-overridable constants (`BVH_ANY_HIT`,
//! `BVH_SHORT_STACK_SIZE`), counters are written only by the `*_counted` entry points, and
//! every entry point is one file specialised with its walk. The wide layout binds its own
//! nodes at binding 0, so a module holds one layout or the other.

use std::borrow::Cow;

use bvhtrace_core::{Precision, Traversal};

use crate::pages::Pages;
use crate::shaders::{self, Wgsl};
use crate::storage::{BvhStorage, RayInput};
use crate::walks::{self, WALKS, Walk};

/// Group of the BVH bindings in the kernels.
pub const BVH_GROUP: u32 = 0;
/// Group of the ray batch bindings (`rays`, `hits`, `counters`) in the kernels.
pub const BATCH_GROUP: u32 = 1;
/// Invocations per workgroup of the entry points (`WORKGROUP_SIZE` in `entry.wgsl`).
pub const WORKGROUP_SIZE: u32 = 64;

/// Where `traverse_common.wgsl`'s leaf visit takes the candidate tests of
/// [`ModuleSet::masks`] and [`ModuleSet::filter`].
const ACCEPT_MARK: &str = "/*BVH_ACCEPT*/";

/// The leaf visit's triangle test (`traverse_common.wgsl`), and what a tree with curves
/// tests instead: the slot's triangle or curve segment (`bvh_curve_buffers.wgsl`).
const TRIANGLE_TEST: &str = "        let tri = bvh_load_triangle(i);
        let h = bvh_intersect_triangle(r, tri.v0, tri.v1, tri.v2);
        let prim = bvh_hit_prim(tri.prim);
";
const SLOT_TEST: &str = "        let slot = bvh_test_slot(r, i, (*best).t);
        let h = slot.hit;
        let prim = slot.prim;
";

/// The triangle test of `precision`: it takes `triangle.wgsl`'s place and defines the same
/// `bvh_intersect_triangle`, so the walks are shared by every precision.
pub fn triangle_wgsl(precision: Precision) -> Wgsl {
    match precision {
        Precision::WatertightF32 => shaders::TRIANGLE,
        Precision::MollerTrumboreF32 => shaders::TRIANGLE_MOLLER_TRUMBORE,
        Precision::WatertightF64 => shaders::TRIANGLE_F64,
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

/// Which entry points a module holds.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Entries {
    /// None: a user's traversal library.
    None,
    /// The hits-only entry point of each walk composed in.
    Plain,
    /// The counted entry point of each walk composed in, and the `counters` binding.
    Counted,
    /// Both.
    All,
}

/// A set of the walks of [`WALKS`].
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct WalkSet(u8);

impl WalkSet {
    /// The walk of `traversal` alone.
    pub fn of(traversal: Traversal) -> WalkSet {
        WalkSet(1 << walks::index(traversal))
    }

    /// Every walk of `layout`'s.
    pub fn of_layout(layout: walks::Layout) -> WalkSet {
        let mut set = WalkSet::default();
        for (i, w) in WALKS.iter().enumerate() {
            if w.layout == layout {
                set.0 |= 1 << i;
            }
        }
        set
    }

    /// The walks in the set, in table order.
    pub fn iter(self) -> impl Iterator<Item = &'static Walk> {
        WALKS
            .iter()
            .enumerate()
            .filter(move |(i, _)| self.0 & (1 << i) != 0)
            .map(|(_, w)| w)
    }

    /// True when some walk of the set reads the escape links.
    pub fn escapes(self) -> bool {
        self.iter().any(|w| w.escapes)
    }

    /// True when the set walks the wide layout (a module then holds that layout only).
    pub fn wide(self) -> bool {
        self.iter().any(Walk::is_wide)
    }
}

/// The WGSL files one module is composed of.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct ModuleSet {
    /// Where the tree's bindings are read from.
    pub storage: BvhStorage,
    /// The triangle test ([`triangle_wgsl`]).
    pub precision: Precision,
    /// The walks composed in, and with them the layout's and the escape links' bindings.
    pub walks: WalkSet,
    /// Attribute modules.
    pub attributes: VertexAttributes,
    /// The instances binding (`bvh_instances.wgsl`), for a two-level BVH.
    pub instances: bool,
    /// Entry points (with `entry.wgsl`, and `entry_counters.wgsl` when counted).
    pub entries: Entries,
    /// Where the entry points read the rays (`entry_rays_*.wgsl`).
    pub rays: RayInput,
    /// The alpha masks (`bvh_alpha_masks.wgsl`, binding 5), asked about every candidate
    /// that would become the hit.
    pub masks: bool,
    /// The name of a WGSL function of yours, `fn(BvhCandidate) -> bool`, asked about every
    /// candidate that would become the hit (after the masks), with `candidate.wgsl`.
    pub filter: Option<&'static str>,
    /// How the tree's arrays in storage buffers are split over bindings
    /// ([`Pages::specialise`]); [`Pages::ONE`] for a tree that fits one binding.
    pub pages: Pages,
    /// A moving mesh's tree (`bvh_motion_buffers.wgsl`, in buffers, in place of the
    /// storage's node and triangle files), and each ray's time (`entry_ray_times.wgsl`)
    /// loaded by the entry points.
    pub motion: bool,
    /// A tree over triangles and curve segments (`bvh_curve_buffers.wgsl` and
    /// `curve.wgsl`, in buffers, in place of the storage's node and triangle files), its
    /// leaves tested slot by slot (`bvh_test_slot`).
    pub curves: bool,
}

impl ModuleSet {
    /// Every walk of the binary layout, no attributes: the everything-on module and, with
    /// `entries`, its kernels.
    pub fn everything(storage: BvhStorage, precision: Precision, entries: Entries) -> ModuleSet {
        ModuleSet {
            storage,
            precision,
            walks: WalkSet::of_layout(walks::Layout::Binary),
            attributes: VertexAttributes::NONE,
            instances: false,
            entries,
            rays: RayInput::Buffer,
            masks: false,
            filter: None,
            pages: Pages::ONE,
            motion: false,
            curves: false,
        }
    }

    /// The full-stack walk over a moving mesh's tree, hits only: what
    /// `bvhtrace_gpu::GpuMotionBvh` traces with.
    pub fn motion() -> ModuleSet {
        ModuleSet {
            walks: WalkSet::of(Traversal::FullStack),
            entries: Entries::Plain,
            motion: true,
            ..ModuleSet::everything(
                BvhStorage::Buffers,
                Precision::WatertightF32,
                Entries::Plain,
            )
        }
    }

    /// The full-stack walk over moving instances joined in one tree
    /// (`MovingInstancesLayout`: a moving top level over static meshes), hits only: what
    /// `bvhtrace_gpu::GpuMotionInstancedBvh` traces with.
    pub fn motion_instances() -> ModuleSet {
        ModuleSet {
            instances: true,
            ..ModuleSet::motion()
        }
    }

    /// The full-stack walk over a tree of triangles and curve segments, hits only: what
    /// `bvhtrace_gpu::GpuCurveBvh` traces with.
    pub fn curves() -> ModuleSet {
        ModuleSet {
            walks: WalkSet::of(Traversal::FullStack),
            entries: Entries::Plain,
            curves: true,
            ..ModuleSet::everything(
                BvhStorage::Buffers,
                Precision::WatertightF32,
                Entries::Plain,
            )
        }
    }

    /// The wide layout's walk in buffers, no attributes, with `entries`. Set `storage` for
    /// textures ([`ModuleSet::wide_in`]).
    pub fn wide(precision: Precision, entries: Entries) -> ModuleSet {
        ModuleSet::wide_in(BvhStorage::Buffers, precision, entries)
    }

    /// [`ModuleSet::wide`] with the wide layout read from `storage`.
    pub fn wide_in(storage: BvhStorage, precision: Precision, entries: Entries) -> ModuleSet {
        ModuleSet {
            walks: WalkSet::of_layout(walks::Layout::Wide),
            ..ModuleSet::everything(storage, precision, entries)
        }
    }

    /// True when the module declares the `counters` binding.
    pub fn has_counters(&self) -> bool {
        matches!(self.entries, Entries::Counted | Entries::All)
    }

    /// True when the module declares the escape links' binding.
    pub fn escapes(&self) -> bool {
        self.walks.escapes() && !self.walks.wide()
    }

    /// The files, in composition order, as `(file name, source)`; an entry point is
    /// `entry_walk.wgsl` specialised for its walk, named after it, and the leaf visit
    /// (`traverse_common.wgsl`) has the masks' and filter's tests when there are some.
    pub fn files(&self) -> Vec<(&'static str, Cow<'static, str>)> {
        let mut out = self.tree_files();
        if self.curves {
            for (name, src) in &mut out {
                if *name == shaders::TRAVERSE_COMMON.0 {
                    *src = src.replace(TRIANGLE_TEST, SLOT_TEST).into();
                }
            }
        }
        if self.masks || self.filter.is_some() {
            for (name, src) in &mut out {
                if *name == shaders::TRAVERSE_COMMON.0 {
                    *src = src.replace(ACCEPT_MARK, &self.accept_test()).into();
                }
            }
        }
        out.extend(self.entry_files());
        out
    }

    /// The bindings, the ray and triangle tests and the walks.
    fn tree_files(&self) -> Vec<(&'static str, Cow<'static, str>)> {
        let wide = self.walks.wide();
        let mut out: Vec<(&'static str, Cow<'static, str>)> = Vec::with_capacity(24);
        out.push((shaders::TYPES.0, shaders::TYPES.1.into()));
        let mut bindings = match (self.motion, wide) {
            _ if self.curves => vec![shaders::BVH_CURVE_BUFFERS, shaders::CURVE],
            (true, _) => vec![shaders::BVH_MOTION_BUFFERS],
            (false, true) => vec![self.storage.wide_wgsl(), self.storage.triangles_wgsl()],
            (false, false) => vec![self.storage.wgsl(), self.storage.triangles_wgsl()],
        };
        if self.escapes() {
            bindings.push(self.storage.escapes_wgsl());
        }
        for (name, src) in bindings {
            out.push(match self.pages.is_one() {
                true => (name, src.into()),
                false => (name, self.pages.specialise(src).into()),
            });
        }
        let mut push = |(name, src): Wgsl| out.push((name, src.into()));
        push(match (self.instances, self.motion) {
            (true, true) => shaders::BVH_MOTION_INSTANCES,
            (true, false) => shaders::BVH_INSTANCES,
            (false, _) => shaders::BVH_NO_INSTANCES,
        });
        if self.masks {
            push(shaders::BVH_ALPHA_MASKS);
        }
        if self.filter.is_some() {
            push(shaders::CANDIDATE);
        }
        for file in [
            shaders::RAY,
            shaders::SURFACE,
            shaders::TEXEL,
            shaders::BOX,
            shaders::TRIANGLE_HIT,
            triangle_wgsl(self.precision),
            shaders::TRAVERSE_COMMON,
            shaders::TRAVERSE_INSTANCES,
        ] {
            push(file);
        }
        if self.walks.iter().next().is_some() {
            push(shaders::TRAVERSE_STACK);
        }
        // A module holds one layout: the wide walk alone, or the binary ones.
        for w in self.walks.iter().filter(|w| w.is_wide() == wide) {
            push(w.file);
        }
        if self.attributes.normals {
            push(shaders::ATTRIBUTE_NORMALS);
        }
        out
    }

    /// The entry points and what they share, as [`ModuleSet::entries`] says.
    fn entry_files(&self) -> Vec<(&'static str, Cow<'static, str>)> {
        let mut out: Vec<(&'static str, Cow<'static, str>)> = Vec::new();
        if self.entries == Entries::None {
            return out;
        }
        out.push((shaders::ENTRY.0, shaders::ENTRY.1.into()));
        let (name, src) = self.rays.wgsl();
        out.push((name, src.into()));
        if self.motion {
            out.push((
                shaders::ENTRY_RAY_TIMES.0,
                shaders::ENTRY_RAY_TIMES.1.into(),
            ));
        }
        if self.has_counters() {
            out.push((shaders::ENTRY_COUNTERS.0, shaders::ENTRY_COUNTERS.1.into()));
        }
        let plain = matches!(self.entries, Entries::Plain | Entries::All);
        let wide = self.walks.wide();
        for w in self.walks.iter().filter(|w| w.is_wide() == wide) {
            for counted in [false, true] {
                if (counted && self.has_counters()) || (!counted && plain) {
                    let i = usize::from(counted);
                    out.push((
                        w.entry_labels[i],
                        entry_point(w, counted, self.motion).into(),
                    ));
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
        join(&self.files(), bvh_group, "")
    }
}

/// `entry_walk.wgsl` specialised as `walk`'s entry point, counted or hits only; with
/// `timed`, the ray's time set as it is loaded.
fn entry_point(walk: &Walk, counted: bool, timed: bool) -> String {
    let call = walk.call_with(
        if timed {
            "bvh_timed_ray(i)"
        } else {
            "bvh_load_ray(i)"
        },
        "BVH_ANY_HIT",
        "BVH_SHORT_STACK_SIZE",
        "lid",
    );
    specialise_entry(walk.entry_points[usize::from(counted)], counted, &call)
}

/// `entry_walk.wgsl` as the entry point `name`, storing what `call` returns (the
/// counters too when `counted`).
pub(crate) fn specialise_entry(name: &str, counted: bool, call: &str) -> String {
    let store = match counted {
        true => "bvh_store_counted",
        false => "bvh_store_hits_only",
    };
    shaders::ENTRY_WALK
        .1
        .replace("BVH_ENTRY_POINT", name)
        .replace("BVH_STORE", store)
        .replace("BVH_WALK", call)
}

/// `parts` after `prefix` (an `enable` line, or nothing), each labelled, the BVH's and the
/// attributes' bindings moved to `@group(bvh_group)`.
pub(crate) fn join(
    parts: &[(&'static str, Cow<'static, str>)],
    bvh_group: u32,
    prefix: &str,
) -> String {
    let mut s = String::with_capacity(32 * 1024);
    s.push_str(prefix);
    let group = format!("@group({bvh_group})");
    for (name, src) in parts {
        s.push_str("// ---- ");
        s.push_str(name);
        s.push_str(" ----\n");
        let rebind = bvh_group != 0 && (name.starts_with("bvh_") || name.starts_with("attribute_"));
        if rebind {
            s.push_str(&src.replace("@group(0)", &group));
        } else {
            s.push_str(src);
        }
        s.push('\n');
    }
    s
}

/// The everything-on kernel module for `storage`: every binary walk with the BVH in group
/// [`BVH_GROUP`], and every entry point of those walks, hits only and counted (batch group
/// [`BATCH_GROUP`]: `rays`, `hits`, `counters`), so any [`crate::KernelKey::entry_point`]
/// of a binary walk is in it (the wide walk's are in its own module). Pipelines use the
/// specialised module of their key ([`crate::KernelKey::source`]) unless a benchmark asks
/// for every module (the `bench-hooks` feature's `Composition::EverythingOn`).
pub fn kernel_source(storage: BvhStorage) -> String {
    kernel_source_for(storage, Precision::WatertightF32)
}

/// [`kernel_source`] with the triangle test of `precision` ([`triangle_wgsl`]).
pub fn kernel_source_for(storage: BvhStorage, precision: Precision) -> String {
    ModuleSet::everything(storage, precision, Entries::All).compose(BVH_GROUP)
}
