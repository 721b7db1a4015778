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

use bvhtrace_core::flat::{ESCAPE_BLOCK, OCTANTS};
use bvhtrace_core::{Precision, Query, TraceOptions, Traversal};

use crate::compose::{BATCH_GROUP, BVH_GROUP, Entries, ModuleSet, VertexAttributes, WalkSet};
use crate::pages::{PAGE_BINDING_STRIDE, PAGE_NAMES, Pages};
use crate::plan::{COUNTERS_BYTES, HIT_BYTES, RAY_BYTES};
use crate::storage::{BvhStorage, RayInput, TEXEL_ROW};
use crate::upload::UploadStats;
use crate::walks::{self, short_stack_size};

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

/// The bindings of the further pages of `whole`'s array when `pages` split it
/// ([`Pages::specialise`] names them): none for pages 0 (`whole` itself) or an array left
/// whole. The first page's binding counts every element (see
/// [`KernelKey::declared_bvh_bytes`]); the others count none.
fn page_bindings(pages: &Pages, whole: BindingInfo) -> Vec<BindingInfo> {
    let count = u32::from(pages.of_binding(whole.binding));
    if whole.group != BVH_GROUP || !whole.uploaded || count <= 1 {
        return Vec::new();
    }
    (1..count)
        .map(|p| BindingInfo {
            binding: whole.binding + PAGE_BINDING_STRIDE * p,
            name: (PAGE_NAMES.iter())
                .find(|(n, _)| *n == whole.name)
                .map_or("", |(_, names)| names[p as usize - 1]),
            per: PerElement::Page,
            ..whole
        })
        .collect()
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
    /// A further page of a split array ([`crate::pages`]): its elements are counted by
    /// the array's first binding.
    Page,
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
    /// The triangle test composed into the module ([`crate::compose::triangle_wgsl`]).
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
    /// How the tree's arrays are split over bindings ([`crate::pages`]): [`Pages::ONE`]
    /// unless the upload is larger than one of the device's bindings.
    pub pages: Pages,
}

impl KernelKey {
    /// The specialised kernel tracing as `opts` says with the BVH (either layout) in
    /// `storage`: rays in buffers, the parallel path kept, positions only.
    pub fn new(storage: BvhStorage, opts: &TraceOptions) -> KernelKey {
        let traversal = match opts.traversal {
            Traversal::ShortStack(_) => {
                Traversal::ShortStack(short_stack_size(opts.traversal).unwrap_or(1))
            }
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
            pages: Pages::ONE,
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

    /// The same key for an upload split into `pages`.
    pub fn with_pages(self, pages: Pages) -> KernelKey {
        KernelKey { pages, ..self }
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
        walks::walk(self.traversal).escapes
    }

    /// The entry point's name: `bvh_trace_{full_stack,short_stack,wide}_{main,counted}`.
    pub fn entry_point(&self) -> &'static str {
        walks::walk(self.traversal).entry_points[usize::from(self.counters)]
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
        if let Some(k) = short_stack_size(self.traversal) {
            c.push(("BVH_SHORT_STACK_SIZE", f64::from(k)));
        }
        c
    }

    /// Every key the tests validate for `storage`: each walk (full stack, stackless,
    /// short stack of size `k`, wide) x query x counters x one mesh or two levels. The
    /// wide keys are the same for every `k` (no ring).
    pub fn all_for_k(storage: BvhStorage, k: u32) -> Vec<KernelKey> {
        let mut v = Vec::new();
        let walks = Traversal::ALL.map(|t| match t {
            Traversal::ShortStack(_) => Traversal::ShortStack(k),
            t => t,
        });
        for traversal in walks {
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
                pages: self.pages,
                ..if walks::walk(self.traversal).is_wide() {
                    ModuleSet::wide_in(self.storage, self.precision, Entries::All)
                } else {
                    ModuleSet::everything(self.storage, self.precision, Entries::All)
                }
            },
            Composition::Specialised => ModuleSet {
                storage: self.storage,
                precision: self.precision,
                walks: WalkSet::of(self.traversal),
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
                pages: self.pages,
                motion: false,
                curves: false,
            },
        }
    }

    /// The composed module (BVH in group [`BVH_GROUP`]).
    pub fn source(&self) -> String {
        self.module_set().compose(BVH_GROUP)
    }

    /// Every binding the module declares, in (group, binding) order. The pipeline binds
    /// those its entry point reads (all of them for [`Composition::Specialised`]).
    pub fn bindings(&self) -> Vec<BindingInfo> {
        let set = self.module_set();
        let textures = set.storage == BvhStorage::Textures;
        let mut b = Vec::new();
        let bvh = |binding, name, element_bytes, per| BindingInfo {
            group: BVH_GROUP,
            binding,
            name,
            element_bytes,
            per,
            uploaded: true,
        };
        let batch = |binding, name, element_bytes| BindingInfo {
            group: BATCH_GROUP,
            binding,
            name,
            element_bytes,
            per: PerElement::Ray,
            uploaded: false,
        };
        let wide = set.walks.wide();
        let (nodes, tris, escapes) = if wide && textures {
            ("bvh_wide_node_texels", "bvh_triangle_texels", "")
        } else if wide {
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
        b.push(bvh(0, nodes, node_bytes(wide), PerElement::Node));
        b.push(bvh(1, tris, 48, PerElement::Triangle));
        if set.escapes() {
            b.push(bvh(2, escapes, ESCAPE_BLOCK_BYTES, PerElement::NodeBlock));
        }
        let paged: Vec<BindingInfo> = b
            .iter()
            .flat_map(|&w| page_bindings(&set.pages, w))
            .collect();
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
            b.push(batch(0, rays, RAY_BYTES));
            b.push(batch(1, hits, HIT_BYTES));
            if set.has_counters() {
                b.push(batch(2, "counters", COUNTERS_BYTES));
            }
        }
        b.extend(paged);
        b.sort_by_key(|x| (x.group, x.binding));
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
                        PerElement::Ray | PerElement::MaskWord | PerElement::Page => 0,
                    }
            })
            .sum()
    }

    /// What an upload for this key holds for a tree of `nodes` nodes, `triangles`
    /// triangles and `instances` instances (`upload_ms` 0): the bindings' bytes
    /// ([`KernelKey::declared_bvh_bytes`]), plus, for textures taller than one row, the
    /// padding of their last row of [`TEXEL_ROW`] texels. For a
    /// [`Traversal::Wide`] key, `nodes` counts the wide tree's nodes: 80 bytes each, five
    /// texels in textures.
    pub fn upload_bytes(&self, nodes: u64, triangles: u64, instances: u64) -> UploadStats {
        let set = self.module_set();
        let wide = set.walks.wide();
        let sized = |elements: u64, element_bytes: u64, texels_per: u64, texel_bytes: u64| match set
            .storage
        {
            BvhStorage::Buffers => elements * element_bytes,
            BvhStorage::Textures => {
                let (row, texels) = (u64::from(TEXEL_ROW), elements * texels_per);
                if texels <= row {
                    texels.max(1) * texel_bytes
                } else {
                    texels.div_ceil(row) * row * texel_bytes
                }
            }
        };
        UploadStats {
            storage: set.storage,
            nodes_bytes: sized(nodes, node_bytes(wide), node_bytes(wide) / 16, 16),
            triangles_bytes: sized(triangles, 48, 3, 16),
            escapes_bytes: if set.escapes() {
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
    /// part present (`escape-links`, `counters`, `vertex-normals`, `instances`,
    /// `alpha-masks`, `pages` for a tree split over bindings, `everything-on`).
    pub fn names(&self) -> Vec<&'static str> {
        let set = self.module_set();
        let mut n = vec![match self.query {
            Query::Any => "any-hit",
            Query::Closest => "closest-hit",
        }];
        n.push(self.traversal.name());
        if set.escapes() {
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
        if !self.pages.is_one() {
            n.push("pages");
        }
        #[cfg(feature = "bench-hooks")]
        if self.composition == Composition::EverythingOn {
            n.push("everything-on");
        }
        n
    }
}
