//! CPU traversals over the flat layout: the full-stack reference and the CPU twins of the
//! GPU kernels (`shaders/traverse_*.wgsl`), step for step.
//!
//! # Hit rule (all traversals, both backends, and the oracle)
//! A triangle hit at `t` replaces the current one when `t_min <= t` and either
//! `t < t_best`, or `t == t_best` and its primitive index is lower. The interval is
//! `[t_min, t_max)`. So the closest hit is the same whatever order the nodes are visited
//! in: among exactly tied triangles, the lowest primitive index wins. For that, a box is
//! culled against the best hit so far only beyond a slack covering how far before the
//! box's entry a triangle inside it can report its f32 `t` (`intersect::BOX_CULL_SLACK`,
//! with its error analysis); the ray's own `t_max` is never widened. Two traversals can
//! then differ only where f32 cannot decide between two triangles (the oracle's
//! `f32_indeterminate` and `f32_t_error_bound`), which the tests check.
//!
//! Any-hit queries stop at the first accepted hit; which triangle that is depends on the
//! visit order, so only hit/miss is compared across traversals.
//!
//! # Panics
//! The traversals expect a [`FlatBvh`] as [`FlatBvh::flatten`] makes it (one that passes
//! [`FlatBvh::check_invariants`]). The stackless and short-stack walks build the escape
//! links on first use ([`FlatBvh::escapes`]), and panic, naming the fix, on links set by
//! hand that do not fit the nodes; the GPU uploads refuse such a tree with an error instead.

use std::fmt;
use std::str::FromStr;

use glam::Vec3;
use rayon::prelude::*;

use crate::flat::{
    FlatBvh, FlatInstance, FlatNode, FlatTriangle, NO_ESCAPE, escape_index, near_far, octant,
};
use crate::intersect::{PreparedRay, intersect_box};
use crate::masks::MaskTables;
use crate::precision::{MollerTrumboreF32, Precision, TriangleTest, WatertightF32, WatertightF64};
use crate::ray::{Counters, Hit, INVALID_RAY, MISS, Ray};
use crate::wide::{WideBvh, WideNode, hit_children};

/// The most short-stack entries a kernel may be specialised for.
pub const MAX_SHORT_STACK: u32 = 32;

/// How the tree is walked.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Traversal {
    /// A stack as deep as the tree; children visited nearest entry distance first.
    /// The reference, and the baseline the others are measured against.
    FullStack,
    /// No stack: one box per step in a deterministic near/far order (Hapala et al. 2011),
    /// going on at the escape (skip) link of every subtree it is done with.
    Stackless,
    /// The same order, with a ring buffer of `k` second-child entries (1..=32). When it
    /// overflows, the oldest entry is dropped; when it runs dry after an overflow, the walk
    /// goes on at the escape link of the node it is done with: exactly the most recent
    /// dropped entry.
    ShortStack(u32),
    /// The wide layout ([`crate::wide`], `FlatBvh::wide`): eight child boxes tested
    /// together per node, hit children visited in the ray octant's slot order, and a
    /// stack of node groups (a node and the hit children it has left).
    Wide,
}

impl Traversal {
    /// The fastest walk on the CPU: the default of [`TraceOptions`] and of the CPU backend.
    pub const CPU_DEFAULT: Traversal = Traversal::FullStack;
    /// The kernels' default walk on a CPU driver (lavapipe, where CI traces them). Each
    /// device tracer reports its own (`Tracer::default_traversal`, from the engine's
    /// `DriverTuning::walk`: the full stack on GPUs, measured fastest there).
    pub const GPU_DEFAULT: Traversal = Traversal::Stackless;

    /// Every walk, one of each kind (the short stack with [`DEFAULT_SHORT_STACK`] entries),
    /// the reference first: the list every front end, report and test takes its walks from.
    pub const ALL: [Traversal; 4] = [
        Traversal::FullStack,
        Traversal::Stackless,
        Traversal::ShortStack(DEFAULT_SHORT_STACK),
        Traversal::Wide,
    ];

    /// Every walk of [`Traversal::ALL`], the short stack once for each of `sizes`: the
    /// list a sweep over walks takes.
    pub fn all_with_short_stacks(sizes: &[u32]) -> Vec<Traversal> {
        (Traversal::ALL.into_iter())
            .flat_map(|t| match t {
                Traversal::ShortStack(_) => {
                    sizes.iter().map(|&k| Traversal::ShortStack(k)).collect()
                }
                t => vec![t],
            })
            .collect()
    }

    /// True when both are the same walk, whatever a short stack's size.
    pub fn same_kind(&self, other: &Traversal) -> bool {
        std::mem::discriminant(self) == std::mem::discriminant(other)
    }

    /// The name used on the command line (`short-stack` for any `k`).
    pub fn name(&self) -> &'static str {
        match self {
            Traversal::FullStack => "full-stack",
            Traversal::Stackless => "stackless",
            Traversal::ShortStack(_) => "short-stack",
            Traversal::Wide => "wide",
        }
    }

    /// True when the traversal reads `FlatBvh::escapes`.
    pub fn needs_escapes(&self) -> bool {
        matches!(self, Traversal::Stackless | Traversal::ShortStack(_))
    }

    /// True when the traversal walks the wide layout (`FlatBvh::wide`).
    pub fn is_wide(&self) -> bool {
        matches!(self, Traversal::Wide)
    }
}

impl fmt::Display for Traversal {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Traversal::ShortStack(k) => write!(f, "short-stack({k})"),
            t => f.write_str(t.name()),
        }
    }
}

impl FromStr for Traversal {
    type Err = String;
    /// `full-stack`, `stackless`, `short-stack` (k = [`DEFAULT_SHORT_STACK`]) or
    /// `short-stack:K`, or `short-stack(K)` as [`Traversal`]'s `Display` prints it.
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "full-stack" => Ok(Traversal::FullStack),
            "stackless" => Ok(Traversal::Stackless),
            "wide" => Ok(Traversal::Wide),
            "short-stack" => Ok(Traversal::ShortStack(DEFAULT_SHORT_STACK)),
            _ => {
                let printed = s
                    .strip_prefix("short-stack(")
                    .and_then(|k| k.strip_suffix(')'));
                if let Some(k) = s.strip_prefix("short-stack:").or(printed) {
                    let k: u32 = k
                        .parse()
                        .map_err(|_| format!("bad short-stack size in '{s}'"))?;
                    if (1..=MAX_SHORT_STACK).contains(&k) {
                        return Ok(Traversal::ShortStack(k));
                    }
                    return Err(format!(
                        "short-stack size must be 1..={MAX_SHORT_STACK}, got {k}"
                    ));
                }
                Err(format!(
                    "unknown traversal '{s}' (expected stackless, short-stack, short-stack:K, full-stack or wide)"
                ))
            }
        }
    }
}

/// Default short-stack size: the largest ring the GPU kernel keeps in registers. On
/// lavapipe it overflows least of the register rings on `bunny_69k` and `igea`, and is the
/// fastest of 2, 4, 6 and 8 by median (tied with 6 on `igea`'s closest hits; README,
/// *Traversals*).
pub const DEFAULT_SHORT_STACK: u32 = 8;

/// Closest hit or any hit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Query {
    /// The nearest hit (with the tie rule above).
    Closest,
    /// Any hit in the interval (occlusion); stops at the first.
    Any,
}

/// Bytes of one binary node as the kernels load it.
const NODE_BYTES: u32 = std::mem::size_of::<FlatNode>() as u32;

/// One ray's walk, counted for the GPU cost model: its [`Counters`], its loop trips (one
/// per node visited, or child taken or group popped in the wide walk: what a kernel's
/// loop spends), and the bytes of nodes and escape links it loaded.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WalkCost {
    /// Box tests (as [`Counters::nodes`]).
    pub nodes: u32,
    /// Triangle tests (as [`Counters::tris`]).
    pub tris: u32,
    /// Trips through the walk's loop.
    pub trips: u32,
    /// Bytes of nodes (32 per binary box tested, 80 per wide node) and escape links
    /// (4 per link followed) loaded.
    pub node_bytes: u32,
}

impl WalkCost {
    /// The counters the backends report.
    pub fn counters(&self) -> Counters {
        Counters {
            nodes: self.nodes,
            tris: self.tris,
        }
    }

    /// Bytes of triangles loaded (48 per triangle tested).
    pub fn triangle_bytes(&self) -> u32 {
        self.tris * std::mem::size_of::<FlatTriangle>() as u32
    }
}

/// The best hit so far, under the walks' one hit rule ([`Best::beats`]); public for walks
/// over other layouts (bvhtrace-cpu), so that every walk takes hits alike.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Best {
    /// Distance of the best hit, or the end of the interval while there is none.
    pub t: f32,
    /// Its primitive id ([`MISS`] while there is none).
    pub prim: u32,
    /// Weight of corner 1.
    pub u: f32,
    /// Weight of corner 2.
    pub v: f32,
    /// True once a hit was taken.
    pub found: bool,
}

impl Best {
    /// No hit yet: the interval ends at the ray's `t_max`.
    #[inline(always)]
    pub fn start(ray: &Ray) -> Best {
        Best {
            t: ray.t_max,
            prim: MISS,
            u: 0.0,
            v: 0.0,
            found: false,
        }
    }

    /// The hit rule: a candidate at `t` on `prim` replaces the best when it is nearer, or
    /// as near with a lower primitive id, which makes the closest hit independent of the
    /// order triangles are tested in.
    #[inline(always)]
    pub fn beats(&self, t: f32, prim: u32) -> bool {
        t < self.t || (t == self.t && self.found && prim < self.prim)
    }

    /// Takes the candidate when it [beats](Best::beats) the best; true when it did.
    #[inline(always)]
    pub fn offer(&mut self, t: f32, prim: u32, u: f32, v: f32) -> bool {
        let taken = self.beats(t, prim);
        if taken {
            *self = Best {
                t,
                prim,
                u,
                v,
                found: true,
            };
        }
        taken
    }

    /// The hit, or a miss at the interval's end.
    #[inline(always)]
    pub fn into_hit(self) -> Hit {
        if self.found {
            Hit {
                t: self.t,
                prim: self.prim,
                u: self.u,
                v: self.v,
            }
        } else {
            Hit::miss(self.t)
        }
    }
}

/// A candidate hit a walk found, nearer than the hit it holds (or as near with a lower
/// primitive): what a [`HitFilter`] accepts or rejects.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Candidate {
    /// The primitive id the hit would report (in two levels, the instance's first id plus
    /// the mesh's primitive).
    pub prim: u32,
    /// In two levels, the instance (an index into [`FlatBvh::instances`]); `None` in one.
    pub instance: Option<u32>,
    /// The primitive in its mesh: `prim` in one level, the mesh's own id in two.
    pub mesh_prim: u32,
    /// Distance along the ray, and the barycentric weights of corners 1 and 2.
    pub t: f32,
    /// Weight of corner 1.
    pub u: f32,
    /// Weight of corner 2.
    pub v: f32,
}

/// Accepts or rejects candidate hits during a walk (Embree's filter functions, an any-hit
/// shader): a rejected candidate is as if the ray had missed that triangle, and the walk
/// goes on. Called only for candidates that would become the hit, so a closest-hit walk
/// calls it for fewer candidates than exist; it must answer the same for the same
/// candidate. Any `Fn(&Candidate) -> bool + Sync` closure is one.
pub trait HitFilter: Sync {
    /// Whether `c` counts as a hit.
    fn accept(&self, c: &Candidate) -> bool;
}

impl<F: Fn(&Candidate) -> bool + Sync> HitFilter for F {
    fn accept(&self, c: &Candidate) -> bool {
        self(c)
    }
}

/// Where a leaf's triangles are tested: the instance's first primitive id and index (two
/// levels), and the filter, if any.
#[derive(Clone, Copy)]
struct Site<'a> {
    prim_base: u32,
    instance: Option<u32>,
    filter: Option<&'a dyn HitFilter>,
    /// The BVH's alpha masks, and where the instance's states start in them.
    masks: Option<&'a MaskTables>,
    mask_base: u32,
}

impl<'a> Site<'a> {
    /// The site of a BVH's triangles, in instance `instance` when there is one.
    #[inline(always)]
    fn new(
        bvh: &'a FlatBvh,
        prim_base: u32,
        instance: Option<u32>,
        filter: Option<&'a dyn HitFilter>,
    ) -> Self {
        let masks = bvh.masks.as_deref();
        Site {
            prim_base,
            instance,
            filter,
            masks,
            mask_base: masks.map_or(0, |m| m.base(instance)),
        }
    }
}

/// Tests a leaf's triangles. Returns true when an any-hit query can stop.
#[inline(always)]
fn visit_leaf<T: TriangleTest>(
    bvh: &FlatBvh,
    r: &PreparedRay,
    n: &FlatNode,
    best: &mut Best,
    c: &mut WalkCost,
    any: bool,
    at: Site<'_>,
) -> bool {
    let first = n.right_or_first as usize;
    let tris = &bvh.triangles[first..first + n.count() as usize];
    visit_triangles::<T>(tris, r, best, c, any, at)
}

/// Tests a run of triangles. Returns true when an any-hit query can stop.
#[inline(always)]
fn visit_triangles<T: TriangleTest>(
    tris: &[FlatTriangle],
    r: &PreparedRay,
    best: &mut Best,
    c: &mut WalkCost,
    any: bool,
    at: Site<'_>,
) -> bool {
    for tri in tris {
        c.tris += 1;
        let [v0, v1, v2] = tri.corners();
        let prim = at.prim_base + tri.prim;
        if let Some(h) = T::intersect(r, v0, v1, v2)
            && best.beats(h.t, prim)
        {
            if let Some(m) = at.masks
                && !m.accept(at.mask_base, tri.prim, h.u, h.v)
            {
                continue;
            }
            if let Some(f) = at.filter {
                let candidate = Candidate {
                    prim,
                    instance: at.instance,
                    mesh_prim: tri.prim,
                    t: h.t,
                    u: h.u,
                    v: h.v,
                };
                if !f.accept(&candidate) {
                    continue;
                }
            }
            *best = Best {
                t: h.t,
                prim,
                u: h.u,
                v: h.v,
                found: true,
            };
            if any {
                return true;
            }
        }
    }
    false
}

#[inline(always)]
fn node_box(n: &FlatNode) -> (Vec3, Vec3) {
    (Vec3::from(n.min), Vec3::from(n.max))
}

/// The two-level state of a walk (the kernels' `traverse_instances.wgsl`): the world ray,
/// and, inside an instance, its primitive base. The walks are specialised on whether the
/// BVH has instances (`I`), so a one-mesh walk carries none of this.
struct Space<'a> {
    bvh: &'a FlatBvh,
    world_ray: &'a Ray,
    world: PreparedRay,
    inside: bool,
    prim_base: u32,
    /// Inside an instance, its index.
    instance: u32,
    mask: u32,
    /// Nodes of the top level in the layout walked.
    top_nodes: u32,
    filter: Option<&'a dyn HitFilter>,
    masks: Option<&'a MaskTables>,
    /// Inside an instance, where its states start in `masks`.
    mask_base: u32,
}

impl<'a> Space<'a> {
    #[inline(always)]
    fn new(
        bvh: &'a FlatBvh,
        ray: &'a Ray,
        world: PreparedRay,
        mask: u8,
        filter: Option<&'a dyn HitFilter>,
    ) -> Self {
        Space {
            bvh,
            world_ray: ray,
            world,
            inside: false,
            prim_base: 0,
            instance: 0,
            mask: u32::from(mask),
            top_nodes: bvh.top_nodes,
            filter,
            masks: bvh.masks.as_deref(),
            mask_base: 0,
        }
    }

    /// Where a leaf's triangles are tested now (`I`: the BVH has instances).
    #[inline(always)]
    fn site<const I: bool>(&self) -> Site<'a> {
        Site {
            prim_base: if I { self.prim_base } else { 0 },
            instance: (I && self.inside).then_some(self.instance),
            filter: self.filter,
            masks: self.masks,
            mask_base: if I { self.mask_base } else { 0 },
        }
    }

    /// Enters the instance of top-level leaf `n`: the ray in its mesh's space, and its
    /// root. `None` (the leaf is done) when the instance's mask shares no bit with the
    /// ray's, or the transformed ray is not valid (a direction scaled to zero or
    /// overflowing).
    #[inline(always)]
    fn enter(&mut self, n: &FlatNode) -> Option<(PreparedRay, u32)> {
        let i = n.right_or_first;
        self.enter_instance(&self.bvh.instances[i as usize], i)
    }

    /// Enters `inst`, instance `index` of the binary BVH (see [`Space::enter`]).
    #[inline(never)]
    fn enter_instance(&mut self, inst: &FlatInstance, index: u32) -> Option<(PreparedRay, u32)> {
        if inst.mask & self.mask == 0 {
            return None;
        }
        let object = inst.ray_to_object(self.world_ray);
        if !object.is_valid() {
            return None;
        }
        self.inside = true;
        self.prim_base = inst.prim_base;
        self.instance = index;
        if let Some(m) = self.masks {
            self.mask_base = m.base(Some(index));
        }
        Some((PreparedRay::new(&object), inst.root))
    }

    /// True (and back in the world) when the walk, inside an instance, goes on at a
    /// top-level node.
    #[inline(always)]
    fn leaves_at(&mut self, node: u32) -> bool {
        let leaves = self.inside && node < self.top_nodes;
        if leaves {
            self.leave();
        }
        leaves
    }

    fn leave(&mut self) {
        self.inside = false;
        self.prim_base = 0;
    }
}

fn full_stack<T: TriangleTest, const I: bool>(
    s: &mut Space,
    best: &mut Best,
    c: &mut WalkCost,
    any: bool,
    stack: &mut Vec<u32>,
) {
    let bvh = s.bvh;
    let mut r = s.world;
    stack.clear();
    c.nodes += 1;
    c.node_bytes += NODE_BYTES;
    let (lo, hi) = node_box(&bvh.nodes[0]);
    if intersect_box(&r, lo, hi, best.t).is_none() {
        return;
    }
    let mut node = 0u32;
    loop {
        c.trips += 1;
        let n = &bvh.nodes[node as usize];
        if n.is_leaf() {
            if I && n.is_instance_leaf() {
                // The mesh's root is walked as the leaf was: its box is not tested again.
                if let Some((object, root)) = s.enter(n) {
                    r = object;
                    node = root;
                    continue;
                }
            } else if visit_leaf::<T>(bvh, &r, n, best, c, any, s.site::<I>()) {
                return;
            }
        } else {
            let (l, rt) = (node + 1, n.right_or_first);
            c.nodes += 2;
            c.node_bytes += 2 * NODE_BYTES;
            let (llo, lhi) = node_box(&bvh.nodes[l as usize]);
            let (rlo, rhi) = node_box(&bvh.nodes[rt as usize]);
            let hl = intersect_box(&r, llo, lhi, best.t);
            let hr = intersect_box(&r, rlo, rhi, best.t);
            match (hl, hr) {
                (Some(tl), Some(tr)) => {
                    let (near, far) = if tr < tl { (rt, l) } else { (l, rt) };
                    stack.push(far);
                    node = near;
                    continue;
                }
                (Some(_), None) => {
                    node = l;
                    continue;
                }
                (None, Some(_)) => {
                    node = rt;
                    continue;
                }
                (None, None) => {}
            }
        }
        match stack.pop() {
            Some(next) => {
                node = next;
                if I && s.leaves_at(node) {
                    r = s.world;
                }
            }
            None => return,
        }
    }
}

/// Short stack of `k` entries; `k == 0` is the stackless walk.
///
/// Both walk the tree depth first, one box test per step: a node's box is tested when the
/// walk arrives at it, and an interior node whose box is hit is entered on the child on the
/// ray's side of its split axis ([`near_far`] for the ray's [`octant`]; Hapala et al.
/// 2011's order). When the walk is done with a node's subtree (its box was missed, or it
/// is a leaf), it goes to the next node of that order:
/// * the stackless walk follows the node's escape link for the octant (a skip link,
///   `FlatBvh::escapes`): no stack, no parent climb, no box tested twice;
/// * the short stack pushes the second child onto a ring of `k` entries when it enters the
///   first, overwriting the oldest entry when the ring is full, and pops it. Only when the
///   ring runs dry after such an overflow does it follow the escape link of the node it is
///   done with, which leads exactly to the most recent dropped entry, so it reads the
///   escape links only on walks deeper than its ring.
///
/// The two visit the same nodes in the same order. `escapes` is `FlatBvh::escapes`, fetched
/// once per ray rather than per node.
fn short_stack<T: TriangleTest, const I: bool>(
    s: &mut Space,
    escapes: &[u32],
    best: &mut Best,
    c: &mut WalkCost,
    any: bool,
    k: u32,
) {
    let bvh = s.bvh;
    let mut r = s.world;
    let world_oct = octant(r.dir);
    let mut oct = world_oct;
    // The top-level leaf of the instance the walk is in: where it goes on once the mesh's
    // walk escapes to `NO_ESCAPE`.
    let mut instance_leaf = 0u32;
    let mut ring = [0u32; MAX_SHORT_STACK as usize];
    let (mut top, mut count) = (0u32, 0u32); // next write slot, live entries
    let mut overflow = false;
    let mut node = 0u32;
    loop {
        c.trips += 1;
        c.nodes += 1;
        c.node_bytes += NODE_BYTES;
        let n = &bvh.nodes[node as usize];
        let (lo, hi) = node_box(n);
        if intersect_box(&r, lo, hi, best.t).is_some() {
            if !n.is_leaf() {
                let (near, far) = near_far(oct, node, n);
                if k > 0 {
                    if count == k {
                        overflow = true; // the oldest entry is overwritten
                    } else {
                        count += 1;
                    }
                    ring[top as usize] = far;
                    top = if top + 1 == k { 0 } else { top + 1 };
                }
                node = near;
                continue;
            }
            if I && n.is_instance_leaf() {
                if let Some((object, root)) = s.enter(n) {
                    r = object;
                    instance_leaf = node;
                    oct = octant(r.dir);
                    node = root;
                    continue;
                }
            } else if visit_leaf::<T>(bvh, &r, n, best, c, any, s.site::<I>()) {
                return;
            }
        }
        // The subtree at `node` is done: the next node is on the ring, or else (after an
        // overflow, or always without a ring) at the escape link.
        if count > 0 {
            top = if top == 0 { k - 1 } else { top - 1 };
            count -= 1;
            node = ring[top as usize];
            if I && s.leaves_at(node) {
                r = s.world;
                oct = world_oct;
            }
            continue;
        }
        if k > 0 && !overflow {
            return;
        }
        // A mesh's walk that escapes to `NO_ESCAPE` goes on at its instance leaf's link.
        loop {
            c.node_bytes += 4;
            let next = escapes[escape_index(node, oct)];
            if next != NO_ESCAPE {
                node = next;
                break;
            }
            if !(I && s.inside) {
                return;
            }
            s.leave();
            r = s.world;
            oct = world_oct;
            node = instance_leaf;
        }
    }
}

/// The wide walk (`Traversal::Wide`): at each node, the eight child boxes are tested
/// together ([`hit_children`]); the hit children are visited in the ray octant's slot
/// order, leaves' triangles at once, interior children by descending into them. What is
/// left of a node's hit children (a *node group*: the node and a mask) is pushed when the
/// walk descends, and popped when the current group runs out. A group holds at most the
/// hit children of one node, so the stack holds at most one group per level.
#[inline(always)]
fn wide<T: TriangleTest, const I: bool, C: ChildTest>(
    s: &mut Space,
    w: &WideBvh,
    best: &mut Best,
    c: &mut WalkCost,
    any: bool,
    stack: &mut Vec<u32>,
) {
    let mut r = s.world;
    let world_oct = octant(r.dir);
    let mut oct = world_oct;
    stack.clear();
    let mut node = 0u32;
    // Groups live in a local array, spilling into `stack` beyond it (any depth).
    let mut local = [[0u32; 2]; LOCAL_GROUPS];
    let mut sp = 0usize;
    // `first`: the child to visit next when it is in `mask` (a fresh group's nearest).
    let (mut mask, mut first) = group::<C>(w, node, &r, best.t, oct, c);
    loop {
        c.trips += 1;
        if mask == 0 {
            // The newest groups are in the spill once the local stack has filled.
            if let (Some(m), Some(n)) = (stack.pop(), stack.pop()) {
                (node, mask) = (n, m);
            } else if sp > 0 {
                sp -= 1;
                [node, mask] = local[sp];
            } else {
                return;
            }
            first = u32::BITS;
            if I && s.leaves_at(node) {
                r = s.world;
                oct = world_oct;
            }
            continue;
        }
        let j = if first < u32::BITS {
            first
        } else {
            mask.trailing_zeros()
        };
        first = u32::BITS;
        mask &= !(1 << j);
        let slot = j as usize ^ oct;
        let n = &w.nodes[node as usize];
        if (n.imask() >> slot) & 1 != 0 {
            if mask != 0 {
                push(&mut local, &mut sp, stack, [node, mask]);
            }
            node = n.child(slot);
            (mask, first) = group::<C>(w, node, &r, best.t, oct, c);
            continue;
        }
        let (start, count) = n.leaf_range(slot);
        if I && node < s.top_nodes {
            let (inst, index) = (
                &w.instances[start as usize],
                w.instance_order[start as usize],
            );
            if let Some((object, root)) = s.enter_instance(inst, index) {
                if mask != 0 {
                    push(&mut local, &mut sp, stack, [node, mask]);
                }
                r = object;
                oct = octant(r.dir);
                node = root;
                (mask, first) = group::<C>(w, node, &r, best.t, oct, c);
            }
            continue;
        }
        let tris = &w.triangles[start as usize..(start + count) as usize];
        if visit_triangles::<T>(tris, &r, best, c, any, s.site::<I>()) {
            return;
        }
    }
}

/// Node groups the wide walk keeps on its own stack frame before it spills to the heap.
const LOCAL_GROUPS: usize = 32;

/// Pushes a node group: on the local array while it has room, else on the spill.
#[inline(always)]
fn push(local: &mut [[u32; 2]; LOCAL_GROUPS], sp: &mut usize, spill: &mut Vec<u32>, g: [u32; 2]) {
    if *sp < LOCAL_GROUPS && spill.is_empty() {
        local[*sp] = g;
        *sp += 1;
    } else {
        spill.extend(g);
    }
}

/// Tests node `node`'s children: the group's mask in visit order, and the box tests
/// counted.
#[inline(always)]
fn group<C: ChildTest>(
    w: &WideBvh,
    node: u32,
    r: &PreparedRay,
    t_best: f32,
    oct: usize,
    c: &mut WalkCost,
) -> (u32, u32) {
    let (hits, first, used) = C::hits(&w.nodes[node as usize], r, t_best, oct);
    c.nodes += used.count_ones();
    c.node_bytes += std::mem::size_of::<WideNode>() as u32;
    (hits, first)
}

/// How the wide walk tests a node's eight boxes: the same bits either way. Returns the
/// hit children in visit order and the used slots.
trait ChildTest {
    fn hits(n: &WideNode, r: &PreparedRay, t_best: f32, oct: usize) -> (u32, u32, u32);
}

/// [`hit_children`], portable.
struct Portable;

impl ChildTest for Portable {
    #[inline(always)]
    fn hits(n: &WideNode, r: &PreparedRay, t_best: f32, oct: usize) -> (u32, u32, u32) {
        let (hits, first) = hit_children(n, r, t_best, oct);
        (hits, first, n.used_mask())
    }
}

/// [`crate::wide::hit_children_avx2`]: only inside [`wide_avx2`].
#[cfg(target_arch = "x86_64")]
struct Avx2;

#[cfg(target_arch = "x86_64")]
impl ChildTest for Avx2 {
    #[inline(always)]
    fn hits(n: &WideNode, r: &PreparedRay, t_best: f32, oct: usize) -> (u32, u32, u32) {
        // SAFETY: `Avx2` is only used by `wide_avx2`, which runs only where AVX2 was
        // detected.
        unsafe { crate::wide::hit_children_avx2(n, r, t_best, oct) }
    }
}

/// One ray of the wide walk, from its checks to its hit.
#[inline(always)]
fn wide_ray<T: TriangleTest, const I: bool, C: ChildTest>(
    bvh: &FlatBvh,
    w: &WideBvh,
    ray: &Ray,
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
    stack: &mut Vec<u32>,
) -> (Hit, WalkCost) {
    let mut c = WalkCost::default();
    if !ray.is_valid() {
        return (untraced(ray), c);
    }
    let mut best = Best::start(ray);
    if w.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
        return (best.into_hit(), c);
    }
    let mut s = Space::new(bvh, ray, PreparedRay::new(ray), opts.mask, filter);
    s.top_nodes = w.top_nodes;
    let any = opts.query == Query::Any;
    wide::<T, I, C>(&mut s, w, &mut best, &mut c, any, stack);
    (best.into_hit(), c)
}

/// A run of rays through the wide walk, appended to `out`: the per-ray setup is inlined
/// into one loop, compiled once per box test.
#[inline(always)]
fn wide_rays<T: TriangleTest, const I: bool, C: ChildTest>(
    bvh: &FlatBvh,
    w: &WideBvh,
    rays: &[Ray],
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
    hits: &mut [Hit],
    costs: &mut [WalkCost],
) {
    let mut stack = Vec::with_capacity(2 * w.depth as usize + 2);
    // A plain loop: an iterator adaptor's `fold` would be compiled apart from the AVX2
    // caller, without its features.
    for i in 0..rays.len() {
        let (h, c) = wide_ray::<T, I, C>(bvh, w, &rays[i], opts, filter, &mut stack);
        hits[i] = h;
        if let Some(slot) = costs.get_mut(i) {
            *slot = c;
        }
    }
}

/// [`wide_rays`] compiled for AVX2 and POPCNT (the caller checks the CPU has them).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,popcnt")]
fn wide_rays_avx2<T: TriangleTest, const I: bool>(
    bvh: &FlatBvh,
    w: &WideBvh,
    rays: &[Ray],
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
    hits: &mut [Hit],
    costs: &mut [WalkCost],
) {
    wide_rays::<T, I, Avx2>(bvh, w, rays, opts, filter, hits, costs)
}

/// [`wide_rays`] with the fastest box test this CPU has.
fn wide_rays_dispatch<T: TriangleTest, const I: bool>(
    bvh: &FlatBvh,
    w: &WideBvh,
    rays: &[Ray],
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
    hits: &mut [Hit],
    costs: &mut [WalkCost],
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("popcnt")
    {
        // SAFETY: AVX2 and POPCNT were just detected.
        return unsafe { wide_rays_avx2::<T, I>(bvh, w, rays, opts, filter, hits, costs) };
    }
    wide_rays::<T, I, Portable>(bvh, w, rays, opts, filter, hits, costs)
}

/// The wide walk over `rays`, into `hits` and (unless it is empty) `costs`, one per ray (one
/// monomorphised loop per precision and level count). Panics, naming the fix, when the BVH
/// has no wide layout.
fn trace_wide(
    bvh: &FlatBvh,
    wide: Option<&WideBvh>,
    rays: &[Ray],
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
    hits: &mut [Hit],
    costs: &mut [WalkCost],
) {
    let Some(w) = wide else {
        panic!(
            "{}: the BVH has no wide layout (call FlatBvh::build_wide)",
            opts.traversal
        );
    };
    match (opts.precision, bvh.is_instanced()) {
        (Precision::WatertightF32, false) => {
            wide_rays_dispatch::<WatertightF32, false>(bvh, w, rays, opts, filter, hits, costs)
        }
        (Precision::WatertightF32, true) => {
            wide_rays_dispatch::<WatertightF32, true>(bvh, w, rays, opts, filter, hits, costs)
        }
        (Precision::MollerTrumboreF32, false) => {
            wide_rays_dispatch::<MollerTrumboreF32, false>(bvh, w, rays, opts, filter, hits, costs)
        }
        (Precision::MollerTrumboreF32, true) => {
            wide_rays_dispatch::<MollerTrumboreF32, true>(bvh, w, rays, opts, filter, hits, costs)
        }
        (Precision::WatertightF64, false) => {
            wide_rays_dispatch::<WatertightF64, false>(bvh, w, rays, opts, filter, hits, costs)
        }
        (Precision::WatertightF64, true) => {
            wide_rays_dispatch::<WatertightF64, true>(bvh, w, rays, opts, filter, hits, costs)
        }
    }
}

/// The hit of a ray that is not traced ([`Ray::is_valid`] is false): `INVALID_RAY` at
/// `t_max` (0 when that is NaN).
pub fn untraced(ray: &Ray) -> Hit {
    Hit {
        prim: INVALID_RAY,
        ..Hit::miss(if ray.t_max.is_nan() { 0.0 } else { ray.t_max })
    }
}

/// What one trace job asks for: the walk, the query, the triangle test, and whether to
/// count each ray's work. Every backend (this crate's CPU walks, the wgpu and ash kernels)
/// takes the same options and gives the same answers for them.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct TraceOptions {
    /// How to walk the tree.
    pub traversal: Traversal,
    /// Closest or any hit.
    pub query: Query,
    /// The triangle test.
    pub precision: Precision,
    /// Also report each ray's [`Counters`].
    pub counters: bool,
    /// The rays' visibility mask: an instance whose mask ([`crate::instance::Instance`])
    /// shares no bit with it is passed through. All bits by default.
    pub mask: u8,
}

impl TraceOptions {
    /// `traversal` and `query` with the watertight f32 test, without counters.
    pub fn new(traversal: Traversal, query: Query) -> Self {
        TraceOptions {
            traversal,
            query,
            precision: Precision::WatertightF32,
            counters: false,
            mask: 0xff,
        }
    }

    /// Closest hits with `traversal`.
    pub fn closest(traversal: Traversal) -> Self {
        Self::new(traversal, Query::Closest)
    }

    /// Any hit with `traversal` (occlusion: shadow and ambient-occlusion rays).
    pub fn any(traversal: Traversal) -> Self {
        Self::new(traversal, Query::Any)
    }

    /// The same options with the triangle test of `precision`.
    pub fn with_precision(self, precision: Precision) -> Self {
        TraceOptions { precision, ..self }
    }

    /// The same options, counting each ray's work or not.
    pub fn with_counters(self, counters: bool) -> Self {
        TraceOptions { counters, ..self }
    }

    /// The same options with the rays' visibility mask `mask`.
    pub fn with_mask(self, mask: u8) -> Self {
        TraceOptions { mask, ..self }
    }
}

impl Default for TraceOptions {
    /// Closest hits with [`Traversal::CPU_DEFAULT`], watertight f32, no counters.
    fn default() -> Self {
        Self::closest(Traversal::CPU_DEFAULT)
    }
}

/// The answer to one batch of rays, from any backend.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TraceOutput {
    /// One hit per ray, in ray order.
    pub hits: Vec<Hit>,
    /// One entry per ray when [`TraceOptions::counters`] was set.
    pub counters: Option<Vec<Counters>>,
    /// Time the kernels took on the device (timestamp queries around the compute pass),
    /// milliseconds; `None` on the CPU and on devices without timestamp queries.
    pub gpu_ms: Option<f64>,
    /// Wall time of the whole call (for a device: uploading the rays, the dispatches and
    /// reading the results back), milliseconds.
    pub wall_ms: f64,
    /// Rays a device kernel gave up on when they spent the adapter's loop-trip budget,
    /// finished on the CPU with the same walk (so the hits and counters are the kernel's
    /// answer). 0 on the CPU and on ordinary scenes.
    pub incomplete: u64,
    /// The traced BVH's instances, for a two-level BVH (`None` for one mesh): what
    /// [`TraceOutput::instance_hit`] splits a hit's primitive id with.
    pub instances: Option<std::sync::Arc<crate::hits::InstanceTable>>,
    /// Where a device trace's wall time went, summed over its submissions; `None` on the
    /// CPU.
    pub phases: Option<TracePhases>,
}

/// Where the wall time of a trace on a device went, measured on the host, milliseconds.
/// With [`TraceOutput::gpu_ms`] (the kernels alone) it tells a slow walk from a slow bus.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TracePhases {
    /// Reading the rays once (the kernel's specialisation), writing them for the device,
    /// and recording and submitting the work.
    pub upload_ms: f64,
    /// From the submission to its completion: the rays' copy to the device, the walk and
    /// the hits' copy back to memory the host can map.
    pub device_ms: f64,
    /// Mapping the hits (and counters) and copying them out.
    pub readback_ms: f64,
}

impl TracePhases {
    /// The phases of one submission from the instants that end them: started, submitted,
    /// completed, and now (its results read back).
    pub fn since(
        started: web_time::Instant,
        submitted: web_time::Instant,
        done: web_time::Instant,
    ) -> TracePhases {
        let ms = |a: web_time::Instant, b: web_time::Instant| (b - a).as_secs_f64() * 1e3;
        TracePhases {
            upload_ms: ms(started, submitted),
            device_ms: ms(submitted, done),
            readback_ms: ms(done, web_time::Instant::now()),
        }
    }
}

impl std::ops::Add for TracePhases {
    type Output = TracePhases;

    /// The three phases of two traces (or submissions) added.
    fn add(self, other: TracePhases) -> TracePhases {
        TracePhases {
            upload_ms: self.upload_ms + other.upload_ms,
            device_ms: self.device_ms + other.device_ms,
            readback_ms: self.readback_ms + other.readback_ms,
        }
    }
}

impl std::ops::AddAssign for TracePhases {
    fn add_assign(&mut self, other: TracePhases) {
        *self = *self + other;
    }
}

/// Traces one ray as `opts` says, returning its hit and its counters (counted whatever
/// `opts.counters` says). `stack` is the full stack's storage, reused across rays.
pub fn trace_ray_with(
    bvh: &FlatBvh,
    ray: &Ray,
    opts: &TraceOptions,
    stack: &mut Vec<u32>,
) -> (Hit, Counters) {
    let (hit, cost) = trace_ray_cost(bvh, ray, opts, stack);
    (hit, cost.counters())
}

/// Traces one ray as [`trace_ray_with`] does, with the walk's whole cost: what the GPU
/// cost model ([`crate::cost`]) reads.
pub fn trace_ray_cost(
    bvh: &FlatBvh,
    ray: &Ray,
    opts: &TraceOptions,
    stack: &mut Vec<u32>,
) -> (Hit, WalkCost) {
    trace_ray_filtered(bvh, ray, opts, None, stack)
}

/// [`trace_ray_cost`] with candidates passed through `filter` (`None`: every candidate
/// counts).
pub fn trace_ray_filtered(
    bvh: &FlatBvh,
    ray: &Ray,
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
    stack: &mut Vec<u32>,
) -> (Hit, WalkCost) {
    trace_ray_in(bvh, bvh.wide().map(|w| &**w), ray, opts, filter, stack)
}

/// [`trace_ray_filtered`] with the wide walk on `wide`, the tree's wide layout held apart
/// from it (collapsed from it with [`WideBvh::collapse`]): so that a tracer needs no copy
/// of the tree to take the wide walk.
pub fn trace_ray_in(
    bvh: &FlatBvh,
    wide: Option<&WideBvh>,
    ray: &Ray,
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
    stack: &mut Vec<u32>,
) -> (Hit, WalkCost) {
    if opts.traversal.is_wide() {
        let (mut hit, mut cost) = ([Hit::miss(0.0)], [WalkCost::default()]);
        trace_wide(
            bvh,
            wide,
            std::slice::from_ref(ray),
            opts,
            filter,
            &mut hit,
            &mut cost,
        );
        return (hit[0], cost[0]);
    }
    let f = filter;
    match opts.precision {
        Precision::WatertightF32 => trace_ray_generic::<WatertightF32>(bvh, ray, opts, f, stack),
        Precision::MollerTrumboreF32 => {
            trace_ray_generic::<MollerTrumboreF32>(bvh, ray, opts, f, stack)
        }
        Precision::WatertightF64 => trace_ray_generic::<WatertightF64>(bvh, ray, opts, f, stack),
    }
}

/// One ray, with the triangle test `T` (monomorphised, so each precision's walk is as
/// fast as if it were the only one).
fn trace_ray_generic<T: TriangleTest>(
    bvh: &FlatBvh,
    ray: &Ray,
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
    stack: &mut Vec<u32>,
) -> (Hit, WalkCost) {
    let (traversal, query, mask) = (opts.traversal, opts.query, opts.mask);
    let mut c = WalkCost::default();
    if !ray.is_valid() {
        return (untraced(ray), c);
    }
    let r = PreparedRay::new(ray);
    let mut best = Best::start(ray);
    if bvh.nodes.is_empty() || !(ray.t_min <= ray.t_max) {
        return (best.into_hit(), c);
    }
    let mut space = Space::new(bvh, ray, r, mask, filter);
    let s = &mut space;
    if traversal.needs_escapes()
        && let Err(e) = bvh.check_escape_links()
    {
        panic!("{traversal}: {e}");
    }
    let any = query == Query::Any;
    let k = match traversal {
        Traversal::FullStack => None,
        Traversal::Stackless => Some(0),
        Traversal::ShortStack(k) => Some(k.clamp(1, MAX_SHORT_STACK)),
        Traversal::Wide => unreachable!("the wide walk is dispatched in trace_ray_with"),
    };
    match (k, bvh.is_instanced()) {
        (None, false) => full_stack::<T, false>(s, &mut best, &mut c, any, stack),
        (None, true) => full_stack::<T, true>(s, &mut best, &mut c, any, stack),
        (Some(k), false) => short_stack::<T, false>(s, bvh.escapes(), &mut best, &mut c, any, k),
        (Some(k), true) => short_stack::<T, true>(s, bvh.escapes(), &mut best, &mut c, any, k),
    }
    (best.into_hit(), c)
}

/// Traces one ray as `opts` says: its hit and its counters.
pub fn trace_ray(bvh: &FlatBvh, ray: &Ray, opts: &TraceOptions) -> (Hit, Counters) {
    trace_ray_with(bvh, ray, opts, &mut Vec::new())
}

/// Traces a batch of rays as `opts` says on all threads of the current rayon pool; the
/// counters are kept only when `opts.counters` is set. `wall_ms` is timed (without the
/// escape links' build, when this is their first use); `gpu_ms` is `None`.
pub fn trace_rays(bvh: &FlatBvh, rays: &[Ray], opts: &TraceOptions) -> TraceOutput {
    trace_rays_filtered(bvh, rays, opts, None)
}

/// [`trace_rays`] with every walk's candidates passed through `filter` (`None`: every
/// candidate counts): alpha-tested geometry, or your own rule (skip the triangle a ray
/// leaves, say).
pub fn trace_rays_filtered(
    bvh: &FlatBvh,
    rays: &[Ray],
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
) -> TraceOutput {
    trace_rays_in(bvh, bvh.wide().map(|w| &**w), rays, opts, filter)
}

/// [`trace_rays_filtered`] with the wide walk on `wide`, held apart from the tree
/// ([`trace_ray_in`]).
pub fn trace_rays_in(
    bvh: &FlatBvh,
    wide: Option<&WideBvh>,
    rays: &[Ray],
    opts: &TraceOptions,
    filter: Option<&dyn HitFilter>,
) -> TraceOutput {
    // The escape links' one-off build on first use is not the walks' time.
    if opts.traversal.needs_escapes() && !rays.is_empty() {
        bvh.escapes();
    }
    let start = web_time::Instant::now();
    let stack = || Vec::with_capacity(bvh.depth as usize + 1);
    let (hits, counters) = if opts.traversal.is_wide() {
        const RUN: usize = 256;
        let mut hits = vec![Hit::miss(0.0); rays.len()];
        let mut costs = vec![WalkCost::default(); if opts.counters { rays.len() } else { 0 }];
        let runs = hits.par_chunks_mut(RUN).zip(rays.par_chunks(RUN));
        if opts.counters {
            runs.zip(costs.par_chunks_mut(RUN))
                .for_each(|((h, r), c)| trace_wide(bvh, wide, r, opts, filter, h, c));
        } else {
            runs.for_each(|(h, r)| trace_wide(bvh, wide, r, opts, filter, h, &mut []));
        }
        let counters = opts
            .counters
            .then(|| costs.iter().map(WalkCost::counters).collect());
        (hits, counters)
    } else if opts.counters {
        let (h, c): (Vec<Hit>, Vec<Counters>) = rays
            .par_iter()
            .with_min_len(256)
            .map_init(stack, |s, ray| {
                let (hit, cost) = trace_ray_in(bvh, wide, ray, opts, filter, s);
                (hit, cost.counters())
            })
            .unzip();
        (h, Some(c))
    } else {
        let h = rays
            .par_iter()
            .with_min_len(256)
            .map_init(stack, |s, ray| {
                trace_ray_in(bvh, wide, ray, opts, filter, s).0
            })
            .collect();
        (h, None)
    };
    TraceOutput {
        hits,
        counters,
        gpu_ms: None,
        wall_ms: start.elapsed().as_secs_f64() * 1e3,
        incomplete: 0,
        instances: crate::hits::InstanceTable::of(bvh),
        phases: None,
    }
}

/// Reference answer by testing every triangle with the test of `precision` and the same
/// hit rule: what every traversal with that precision must return exactly, for
/// closest-hit queries.
pub fn brute_force(bvh: &FlatBvh, ray: &Ray, precision: Precision) -> Hit {
    brute_force_filtered(bvh, ray, precision, None)
}

/// [`brute_force`] with candidates passed through `filter`, in the order of the triangles:
/// what the filtered walks must return for closest-hit queries.
pub fn brute_force_filtered(
    bvh: &FlatBvh,
    ray: &Ray,
    precision: Precision,
    filter: Option<&dyn HitFilter>,
) -> Hit {
    let f = filter;
    match precision {
        Precision::WatertightF32 => brute_force_generic::<WatertightF32>(bvh, ray, f),
        Precision::MollerTrumboreF32 => brute_force_generic::<MollerTrumboreF32>(bvh, ray, f),
        Precision::WatertightF64 => brute_force_generic::<WatertightF64>(bvh, ray, f),
    }
}

fn brute_force_generic<T: TriangleTest>(
    bvh: &FlatBvh,
    ray: &Ray,
    filter: Option<&dyn HitFilter>,
) -> Hit {
    if !ray.is_valid() {
        return trace_ray(bvh, ray, &TraceOptions::closest(Traversal::FullStack)).0;
    }
    let r = PreparedRay::new(ray);
    let mut best = Best::start(ray);
    if bvh.is_instanced() {
        if ray.t_min <= ray.t_max {
            brute_force_instances::<T>(bvh, ray, filter, &mut best);
        }
        return best.into_hit();
    }
    if ray.t_min <= ray.t_max {
        let leaf = FlatNode {
            min: [0.0; 3],
            right_or_first: 0,
            max: [0.0; 3],
            meta: (bvh.triangles.len() as u32) << 2,
        };
        visit_leaf::<T>(
            bvh,
            &r,
            &leaf,
            &mut best,
            &mut WalkCost::default(),
            false,
            Site::new(bvh, 0, None, filter),
        );
    }
    best.into_hit()
}

/// Every triangle of every instance (each leaf of each mesh reached from an instance,
/// whatever its box), with the walks' ray transform.
fn brute_force_instances<T: TriangleTest>(
    bvh: &FlatBvh,
    ray: &Ray,
    filter: Option<&dyn HitFilter>,
    best: &mut Best,
) {
    let mut stack = Vec::new();
    for (index, inst) in bvh.instances.iter().enumerate() {
        let object = inst.ray_to_object(ray);
        if !object.is_valid() {
            continue;
        }
        let r = PreparedRay::new(&object);
        stack.push(inst.root);
        while let Some(i) = stack.pop() {
            let n = &bvh.nodes[i as usize];
            if n.is_leaf() {
                let mut c = WalkCost::default();
                let at = Site::new(bvh, inst.prim_base, Some(index as u32), filter);
                visit_leaf::<T>(bvh, &r, n, best, &mut c, false, at);
            } else {
                stack.extend([i + 1, n.right_or_first]);
            }
        }
    }
}
