//! What one trace job needs, and the pipeline built from exactly that.
//!
//! A [`PipelineFeatures`] says what the job uses (the traversal, hence whether the escape
//! links are read; closest or any hit; counters; per-vertex attributes the scene has and the
//! job shades with) and is the key of [`crate::GpuContext`]'s pipeline cache. From it come
//!
//! * the WGSL module ([`PipelineFeatures::source`]): composed of only the files the job
//!   needs ([`ModuleSet`]): no escape-link binding or escape-link walk for the full stack, no
//!   `counters` binding unless counters are on, no attribute module for a positions-only
//!   scene, one entry point;
//! * the bindings that module declares ([`PipelineFeatures::bindings`], checked against a
//!   naga reflection of the composed source by `crates/gpu/tests/features.rs`);
//! * the upload ([`PipelineFeatures::upload_options`]): the escape links only when read.
//!
//! Closest/any hit and the short-stack size stay override constants (folded when the
//! pipeline is created). [`Composition::EverythingOn`] composes every module instead (the
//! module [`crate::kernel_source`] returns), for comparison.

use bvhtrace_core::flat::{ESCAPE_BLOCK, OCTANTS};
use bvhtrace_core::{Precision, Query, Traversal};

use crate::bvh::{UploadOptions, UploadStats};
use crate::shaders::{self, BvhStorage, KernelVariant};

/// Bytes of one block of escape links ([`PerElement::NodeBlock`]).
const ESCAPE_BLOCK_BYTES: u64 = (ESCAPE_BLOCK * OCTANTS * 4) as u64;

/// Blocks of escape links for `nodes` nodes.
fn escape_blocks(nodes: u64) -> u64 {
    nodes.div_ceil(ESCAPE_BLOCK as u64)
}

/// `bvh_buffers_escapes.wgsl`.
pub const BVH_BUFFERS_ESCAPES_WGSL: &str =
    include_str!("../../../shaders/bvh_buffers_escapes.wgsl");
/// `bvh_textures_escapes.wgsl`.
pub const BVH_TEXTURES_ESCAPES_WGSL: &str =
    include_str!("../../../shaders/bvh_textures_escapes.wgsl");
/// `entry_counters.wgsl`: the `counters` binding, composed only when counters are on.
pub const ENTRY_COUNTERS_WGSL: &str = include_str!("../../../shaders/entry_counters.wgsl");
/// `attribute_normals.wgsl`: per-vertex normals, composed only when the scene has them and
/// the job shades with them.
pub const ATTRIBUTE_NORMALS_WGSL: &str = include_str!("../../../shaders/attribute_normals.wgsl");

/// The entry-point files: `(file, source)` for `[full stack, short stack]` x
/// `[hits only, counted]`, each holding the entry point [`KernelVariant::entry_point`]
/// names.
pub const ENTRY_POINT_FILES: [[(&str, &str); 2]; 2] = [
    [
        (
            "entry_full_stack.wgsl",
            include_str!("../../../shaders/entry_full_stack.wgsl"),
        ),
        (
            "entry_full_stack_counted.wgsl",
            include_str!("../../../shaders/entry_full_stack_counted.wgsl"),
        ),
    ],
    [
        (
            "entry_short_stack.wgsl",
            include_str!("../../../shaders/entry_short_stack.wgsl"),
        ),
        (
            "entry_short_stack_counted.wgsl",
            include_str!("../../../shaders/entry_short_stack_counted.wgsl"),
        ),
    ],
];

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
    /// ([`crate::kernel_source`]): the baseline the benchmark compares against.
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
    /// The BVH bindings file.
    pub storage: BvhStorage,
    /// The triangle test ([`shaders::triangle_wgsl`]).
    pub precision: Precision,
    /// The escape-link binding (`bvh_*_escapes.wgsl`).
    pub escapes: bool,
    /// `traverse_full_stack.wgsl`.
    pub full_stack: bool,
    /// `traverse_short_stack.wgsl` (needs `escapes`).
    pub short_stack: bool,
    /// Attribute modules.
    pub attributes: VertexAttributes,
    /// Entry points (with `entry.wgsl`, and `entry_counters.wgsl` when counted).
    pub entries: Entries,
    /// Where the entry points read the rays (`entry_rays_*.wgsl`).
    pub rays: shaders::RayInput,
}

impl ModuleSet {
    /// Everything but attributes: the library and, with `entries`, the kernels.
    pub fn everything(storage: BvhStorage, precision: Precision, entries: Entries) -> ModuleSet {
        ModuleSet {
            storage,
            precision,
            escapes: true,
            full_stack: true,
            short_stack: true,
            attributes: VertexAttributes::NONE,
            entries,
            rays: shaders::RayInput::Buffer,
        }
    }

    /// True when the module declares the `counters` binding.
    pub fn has_counters(&self) -> bool {
        matches!(self.entries, Entries::Counted | Entries::All)
    }

    /// The files, in composition order, as `(file name, source)`.
    pub fn files(&self) -> Vec<(&'static str, &'static str)> {
        let mut out = Vec::with_capacity(16);
        for (i, &(name, src)) in shaders::SHADER_FILES.iter().enumerate() {
            match name {
                "traverse_stack.wgsl" if !(self.full_stack || self.short_stack) => {}
                "traverse_full_stack.wgsl" if !self.full_stack => {}
                "traverse_short_stack.wgsl" if !self.short_stack => {}
                "triangle.wgsl" => out.push(shaders::triangle_wgsl(self.precision)),
                _ => out.push((name, src)),
            }
            if i == 0 {
                out.push(self.storage.wgsl());
                if self.escapes {
                    out.push(self.storage.escapes_wgsl());
                }
            }
        }
        if self.attributes.normals {
            out.push(("attribute_normals.wgsl", ATTRIBUTE_NORMALS_WGSL));
        }
        if self.entries == Entries::None {
            return out;
        }
        out.push(("entry.wgsl", shaders::ENTRY_WGSL));
        out.push(self.rays.wgsl());
        if self.has_counters() {
            out.push(("entry_counters.wgsl", ENTRY_COUNTERS_WGSL));
        }
        let plain = matches!(self.entries, Entries::Plain | Entries::All);
        let counted = self.has_counters();
        for (walk, present) in [self.full_stack, self.short_stack].into_iter().enumerate() {
            if present && plain {
                out.push(ENTRY_POINT_FILES[walk][0]);
            }
            if present && counted {
                out.push(ENTRY_POINT_FILES[walk][1]);
            }
        }
        out
    }

    /// The composed WGSL, the BVH bindings (and attribute bindings) in `@group(bvh_group)`.
    pub fn compose(&self, bvh_group: u32) -> String {
        let mut s = String::with_capacity(24 * 1024);
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
                s.push_str(src);
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
    /// One element per ray of the batch.
    Ray,
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

/// Everything that decides one trace pipeline, and the key of the pipeline cache.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct PipelineFeatures {
    /// Storage, traversal, query, counters (and whatever else selects the kernel).
    pub variant: KernelVariant,
    /// Per-vertex attributes composed in ([`VertexAttributes::needed`]).
    pub attributes: VertexAttributes,
    /// Only what is needed, or everything.
    pub composition: Composition,
}

impl PipelineFeatures {
    /// The specialised pipeline for `variant`, positions only.
    pub fn new(variant: KernelVariant) -> PipelineFeatures {
        PipelineFeatures {
            variant,
            attributes: VertexAttributes::NONE,
            composition: Composition::Specialised,
        }
    }

    /// The pipeline for a job: `traversal` and `query` on `storage`, counters when asked
    /// for, and the attributes the scene has and the job uses; the rays read as
    /// [`crate::GpuBvh::trace`] uploads them ([`shaders::RayInput::for_storage`]).
    pub fn for_job(
        storage: BvhStorage,
        traversal: Traversal,
        query: Query,
        counters: bool,
        scene_has: VertexAttributes,
        job_uses: VertexAttributes,
    ) -> PipelineFeatures {
        PipelineFeatures {
            attributes: VertexAttributes::needed(scene_has, job_uses),
            ..Self::new(
                KernelVariant::new(storage, traversal, query, counters)
                    .with_rays(shaders::RayInput::for_storage(storage)),
            )
        }
    }

    /// The same features, composed as `composition` says.
    pub fn with_composition(mut self, composition: Composition) -> PipelineFeatures {
        self.composition = composition;
        self
    }

    /// The files the module is composed of.
    pub fn module_set(&self) -> ModuleSet {
        let v = &self.variant;
        match self.composition {
            Composition::EverythingOn => ModuleSet {
                rays: v.rays,
                ..ModuleSet::everything(v.storage, v.precision, Entries::All)
            },
            Composition::Specialised => ModuleSet {
                storage: v.storage,
                precision: v.precision,
                escapes: v.needs_escapes(),
                full_stack: !v.short_stack,
                short_stack: v.short_stack,
                attributes: self.attributes,
                entries: if v.counters {
                    Entries::Counted
                } else {
                    Entries::Plain
                },
                rays: v.rays,
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
        let (nodes, tris, escapes) = if textures {
            (
                "bvh_node_texels",
                "bvh_triangle_texels",
                "bvh_escape_texels",
            )
        } else {
            ("bvh_nodes", "bvh_triangles", "bvh_escapes")
        };
        b.push(bvh(0, nodes, 32, PerElement::Node));
        b.push(bvh(1, tris, 48, PerElement::Triangle));
        if set.escapes {
            b.push(bvh(2, escapes, ESCAPE_BLOCK_BYTES, PerElement::NodeBlock));
        }
        if set.attributes.normals {
            b.push(bvh(3, "vertex_normals", 48, PerElement::Triangle));
        }
        if set.entries != Entries::None {
            let (rays, hits) = match set.rays {
                shaders::RayInput::Buffer => ("rays", "hits"),
                shaders::RayInput::Texture => ("ray_texels", "hit_texels"),
            };
            b.push(batch(0, rays, crate::trace::RAY_BYTES));
            b.push(batch(1, hits, crate::trace::HIT_BYTES));
            if set.has_counters() {
                b.push(batch(2, "counters", crate::trace::COUNTERS_BYTES));
            }
        }
        b
    }

    /// Bytes the BVH bindings declare for a tree of `nodes` nodes and `triangles`
    /// triangles: what a [`BvhStorage::Buffers`] upload for these features holds (texture
    /// uploads add row padding).
    pub fn declared_bvh_bytes(&self, nodes: u64, triangles: u64) -> u64 {
        self.bindings()
            .iter()
            .filter(|b| b.uploaded)
            .map(|b| {
                b.element_bytes
                    * match b.per {
                        PerElement::Node => nodes,
                        PerElement::NodeBlock => escape_blocks(nodes),
                        PerElement::Triangle => triangles,
                        PerElement::Ray => 0,
                    }
            })
            .sum()
    }

    /// What [`crate::GpuBvh::upload`] with [`PipelineFeatures::upload_options`] uploads for
    /// a tree of `nodes` nodes and `triangles` triangles (`upload_ms` 0): the bindings'
    /// bytes ([`PipelineFeatures::declared_bvh_bytes`]), plus, for textures taller than one
    /// row, the padding of their last row of [`crate::TEXEL_ROW`] texels.
    pub fn upload_bytes(&self, nodes: u64, triangles: u64) -> UploadStats {
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
            nodes_bytes: sized(nodes, 32, 2, 16),
            triangles_bytes: sized(triangles, 48, 3, 16),
            escapes_bytes: if set.escapes {
                sized(
                    escape_blocks(nodes),
                    ESCAPE_BLOCK_BYTES,
                    ESCAPE_BLOCK_BYTES / 4,
                    4,
                )
            } else {
                0
            },
            upload_ms: 0.0,
        }
    }

    /// The traversal the variant walks.
    pub fn traversal(&self) -> Traversal {
        self.variant.traversal()
    }

    /// The upload these features read: the escape links only when the traversal reads them.
    pub fn upload_options(&self) -> UploadOptions {
        UploadOptions::for_traversal(self.traversal()).with_storage(self.variant.storage)
    }

    /// What was included, in words, for listings: the query, the walk, and each optional
    /// part present (`escape-links`, `counters`, `vertex-normals`, `everything-on`).
    pub fn names(&self) -> Vec<&'static str> {
        let v = &self.variant;
        let set = self.module_set();
        let mut n = vec![if v.any_hit { "any-hit" } else { "closest-hit" }];
        n.push(match self.traversal() {
            Traversal::FullStack => "full-stack",
            Traversal::Stackless => "stackless",
            Traversal::ShortStack(_) => "short-stack",
        });
        if set.escapes {
            n.push("escape-links");
        }
        if v.counters {
            n.push("counters");
        }
        if set.attributes.normals {
            n.push("vertex-normals");
        }
        if self.composition == Composition::EverythingOn {
            n.push("everything-on");
        }
        n
    }
}

impl KernelVariant {
    /// The specialised module for this variant: only the files it needs (see
    /// [`PipelineFeatures`]); [`crate::kernel_source`] is the everything-on module.
    pub fn source(&self) -> String {
        PipelineFeatures::new(*self).source()
    }
}
